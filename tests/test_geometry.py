"""keyshape.base.geometry: rigid and similarity fits against known motions, in 2D and 3D."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from keyshape.base.geometry import apply_affine, apply_rigid, fit_similarity, procrustes_mean, rigid_fit, robust_rigid_fit


def _rot2(a):
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


@settings(max_examples=30, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(0.2, 5.0), st.integers(0, 2**31 - 1))
def test_similarity_2d_recovers_a_known_motion(angle, scale, seed):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(12, 2))
    true = np.hstack([scale * _rot2(angle), rng.normal(size=(2, 1)) * 10])
    np.testing.assert_allclose(fit_similarity(src, apply_affine(true, src)), true, atol=1e-9)


def test_rigid_fit_weights_and_gaps_3d():
    rng = np.random.default_rng(3)
    ref = rng.normal(size=(8, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    frames = (ref @ q.T + [1.0, 2.0, 3.0])[None].repeat(2, 0)
    frames[0, 5:] += 50.0                       # outliers with weight 0 do not move the fit
    frames[1, 0] = np.nan                       # a gap is weight 0
    w = np.ones((2, 8))
    w[0, 5:] = 0
    rot, trans, sc = rigid_fit(ref, frames, w)
    np.testing.assert_allclose(rot, np.stack([q, q]), atol=1e-10)
    np.testing.assert_allclose(trans, [[1.0, 2.0, 3.0]] * 2, atol=1e-10)
    np.testing.assert_allclose(apply_rigid(frames[1:, 1:], rot[1:], trans[1:], inverse=True)[0], ref[1:], atol=1e-10)
    rot, trans, _ = rigid_fit(ref[:2], frames[:1, :2])               # under-determined: NaN, not a guess
    assert np.isnan(rot).all() and np.isnan(trans).all()


def test_procrustes_mean_ignores_similarity_motions():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(10, 2))
    shapes = np.stack([apply_affine(np.hstack([s * _rot2(a), t[:, None]]), base + rng.normal(scale=0.01, size=base.shape))
                       for s, a, t in zip(rng.uniform(0.5, 2, 6), rng.uniform(-1, 1, 6), rng.normal(size=(6, 2)))])
    mean = procrustes_mean(shapes)
    assert np.linalg.norm(mean) == pytest.approx(1.0, abs=1e-3) and np.abs(mean.mean(0)).max() < 1e-12
    ref = base - base.mean(0)
    ref /= np.linalg.norm(ref)
    aligned = apply_affine(fit_similarity(mean, ref), mean)        # same shape as the noise-free base
    assert np.abs(aligned - ref).max() < 0.01


def _rigid_take(seed, n_frames=40, n_points=6):
    """Exact rigid motion of ``n_points`` 3D points (a head jig) with known pose per frame."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (n_points, 3))
    rot = Rotation.from_rotvec(0.4 * rng.normal(size=(n_frames, 3))).as_matrix()
    trans = rng.normal(0, 30, (n_frames, 3))
    return ref, np.einsum("fij,pj->fpi", rot, ref) + trans[:, None], rot, trans


def test_robust_rigid_fit_rejects_a_displaced_point_and_keeps_clean_frames_exact():
    ref, frames, rot, trans = _rigid_take(0)
    x = frames.copy()
    bad = [3, 11, 25]
    x[bad, [2, 4, 0]] += [[25.0, 0, 0], [0, -15.0, 5.0], [8.0, 8.0, 8.0]]      # knocked / mislabelled markers
    x[30, 1] = np.nan                                                          # a gap is neither fitted nor rejected
    plain_rot, plain_trans, _ = rigid_fit(ref, x)
    assert np.abs(plain_rot[bad] - rot[bad]).max() > 1e-2                      # least squares is pulled off
    r, t, rej = robust_rigid_fit(ref, x, threshold=1e-6)
    np.testing.assert_allclose(r, rot, atol=1e-9)
    np.testing.assert_allclose(t, trans, atol=1e-7)
    expect = np.zeros(x.shape[:2], bool)
    expect[bad, [2, 4, 0]] = True
    np.testing.assert_array_equal(rej, expect)
    clean = np.setdiff1d(np.arange(len(x)), bad)
    assert np.array_equal(r[clean], plain_rot[clean]) and np.array_equal(t[clean], plain_trans[clean])
    # two of four markers wrong: no consensus of 3, the plain fit is kept and nothing is claimed
    y = frames[:1, :4].copy()
    y[0, :2] += [[20.0, 0, 0], [0, 0, -30.0]]
    r1, t1, rej1 = robust_rigid_fit(ref[:4], y, threshold=1e-6)
    np.testing.assert_array_equal(r1, rigid_fit(ref[:4], y)[0])
    assert not rej1.any()


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 5), st.floats(5.0, 100.0))
def test_robust_rigid_fit_is_rigidly_equivariant(seed, bad, shift):
    """Moving every frame by one rigid motion G moves every fitted pose by G and rejects the same markers."""
    from scipy.spatial.transform import Rotation
    ref, frames, rot, trans = _rigid_take(seed, n_frames=4)
    rng = np.random.default_rng(seed + 1)
    x = frames.copy()
    x[1:3, bad] += shift * Rotation.random(random_state=seed).as_matrix()[0]
    g_rot = Rotation.random(random_state=seed + 2).as_matrix()
    g_t = rng.normal(0, 100, 3)
    r, t, rej = robust_rigid_fit(ref, x, threshold=1e-6)
    r2, t2, rej2 = robust_rigid_fit(ref, x @ g_rot.T + g_t, threshold=1e-6)
    np.testing.assert_array_equal(rej2, rej)
    assert rej[1:3, bad].all() and rej.sum() == 2
    np.testing.assert_allclose(r2, np.einsum("ij,fjk->fik", g_rot, r), atol=1e-9)
    np.testing.assert_allclose(t2, t @ g_rot.T + g_t, atol=1e-7)
    np.testing.assert_allclose(r, rot, atol=1e-9)
