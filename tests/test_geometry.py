"""keyshape.base.geometry: rigid and similarity fits against known motions, in 2D and 3D."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from keyshape.base.geometry import apply_affine, apply_rigid, fit_similarity, procrustes_mean, rigid_fit


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
