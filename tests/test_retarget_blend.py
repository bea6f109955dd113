"""Blending, regions, head pose and the retargeter (paper 004, section 5)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import nnls

from keyshape.base.errors import InputError, NotFittedError
from keyshape.retarget.targets.blend import BlendBasis, blend, mesh_edges, region_weights
from keyshape.retarget.headpose import head_motion, hold_invalid, similarity
from keyshape.retarget.targets.retargeter import Retargeter
from keyshape.retarget.targets.target_set import TargetSet


def grid(nx=21, ny=11, h=1.0):
    """A flat grid mesh in z=0 (quads), spacing ``h``."""
    x, y = np.meshgrid(np.arange(nx) * h, np.arange(ny) * h)
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i = np.arange(nx * ny).reshape(ny, nx)
    quads = np.stack([i[:-1, :-1], i[:-1, 1:], i[1:, 1:], i[1:, :-1]], axis=-1).reshape(-1, 4)
    return v, list(quads)


@pytest.mark.parametrize("form", ["absolute", "delta"])
@pytest.mark.parametrize("seed", [0, 1])
def test_one_hot_gives_exactly_the_target(form, seed):
    rng = np.random.default_rng(seed)
    b = rng.normal(size=(5, 30, 3))
    n = rng.normal(size=(30, 3))
    out = blend(np.eye(5), b, neutral=n, form=form)
    if form == "absolute":
        np.testing.assert_array_equal(out, b)      # exact: one-hot rows pick a row of the basis
    else:                                          # N + (B - N): exact up to rounding of the subtraction
        np.testing.assert_allclose(out, b, rtol=0, atol=4 * np.finfo(float).eps * np.abs(b).max())


def test_absolute_and_delta_differ_by_unspent_weight_times_neutral():
    rng = np.random.default_rng(2)
    b, n = rng.normal(size=(4, 20, 3)), rng.normal(size=(20, 3))
    w = rng.uniform(0, 1, size=(50, 4))        # NNLS-like: rows do not sum to one
    a, d = blend(w, b, n, "absolute"), blend(w, b, n, "delta")
    np.testing.assert_allclose(d - a, (1 - w.sum(1))[:, None, None] * n, atol=1e-12)
    w1 = w / w.sum(1, keepdims=True)            # affine weights: the forms agree
    np.testing.assert_allclose(blend(w1, b, n, "absolute"), blend(w1, b, n, "delta"), atol=1e-12)


def test_one_default_form_for_blend_basis_and_retargeter():
    """``blend``, ``BlendBasis`` and ``Retargeter`` share the default "auto": delta when a neutral is
    given (it is never silently ignored), absolute without one."""
    from keyshape.retarget.targets.target_set import TargetSet
    rng = np.random.default_rng(8)
    b, n = rng.normal(size=(4, 20, 3)), rng.normal(size=(20, 3))
    w = rng.uniform(0, 1, size=(6, 4))
    np.testing.assert_array_equal(blend(w, b, neutral=n), blend(w, b, n, "delta"))
    np.testing.assert_array_equal(blend(w, b), blend(w, b, form="absolute"))
    assert np.abs(blend(w, b, neutral=n) - blend(w, b, n, "absolute")).max() > 0.1
    assert BlendBasis().fit(b, n).form_ == "delta" and BlendBasis().fit(b).form_ == "absolute"
    names = [f"k{i}" for i in range(4)]
    rt = Retargeter().fit(TargetSet(names, names, b, [None] * 4, n))
    assert rt.form_ == "delta"
    np.testing.assert_allclose(rt.transform(w), blend(w, b, neutral=n), atol=1e-12)


def test_blend_matches_reference_and_chunking_and_float32():
    rng = np.random.default_rng(3)
    b, w = rng.normal(size=(6, 40, 3)), rng.uniform(0, 1.3, size=(37, 6))
    ref = np.einsum("fk,kvd->fvd", w, b)
    bb = BlendBasis().fit(b)
    np.testing.assert_allclose(bb.transform(w), ref, atol=1e-12)
    np.testing.assert_allclose(bb.transform(w, chunk_frames=5), ref, atol=1e-12)
    out32 = np.empty((37, 40, 3), np.float32)
    bb32 = BlendBasis(dtype=np.float32).fit(b)
    assert bb32.transform(w, out=out32) is out32
    np.testing.assert_allclose(out32, ref, atol=1e-5)


def test_identity_2d_targets_equal_to_source_keys_reproduce_decomposed_frames(tmp_path):
    """Targets = the source key shapes (as .pts files): retargeting gives back sum w_i S_i, the
    decomposed source frames, and the source frames themselves where they lie in the keys' cone."""
    from keyshape.retarget.targets.target_set import load_targets
    from keyshape.base.formats.labels import read_pts, write_pts
    rng = np.random.default_rng(4)
    cols = [f"mouth_{i}" for i in range(6)]
    for c in cols:
        write_pts(tmp_path / f"{c}.pts", rng.normal(size=(48, 2)) * 10 + 100)
    keys = np.stack([read_pts(tmp_path / f"{c}.pts") for c in cols])    # the source key shapes
    true_w = rng.uniform(0, 0.5, size=(40, 6))
    frames = np.einsum("fk,kpd->fpd", true_w, keys) + rng.normal(scale=0.05, size=(40, 48, 2))
    a = keys.reshape(6, -1).T
    w = np.stack([nnls(a, f.ravel())[0] for f in frames])
    ts = load_targets(cols, tmp_path)
    out = Retargeter().fit(ts).transform(w)
    np.testing.assert_allclose(out, np.einsum("fk,kpd->fpd", w, keys), atol=1e-9)
    assert np.abs(out - frames).max() < 0.5       # noise 0.05 px: reconstruction close to the source
    noiseless = np.einsum("fk,kpd->fpd", true_w, keys)
    w0 = np.stack([nnls(a, f.ravel())[0] for f in noiseless])
    np.testing.assert_allclose(Retargeter().fit(ts).transform(w0), noiseless, atol=1e-8)


def test_region_weights_partition_and_linear_band():
    v, quads = grid(41, 5)
    left, right = np.flatnonzero(v[:, 0] <= 5), np.flatnonzero(v[:, 0] >= 35)
    rw = region_weights(v, [left, right], band=10.0)
    np.testing.assert_allclose(rw.sum(0), 1.0)
    assert rw.min() >= 0 and rw.max() <= 1
    x = v[:, 0]
    assert np.all(rw[0, x <= 14] == 1.0) and np.all(rw[1, x >= 26] == 1.0)
    np.testing.assert_allclose(rw[0, x == 20], 0.5)            # midline
    mono = rw[0][np.argsort(x, kind="stable")][::5]
    assert np.all(np.diff(mono) <= 1e-12)                        # falls off monotonically
    geo = region_weights(v, [left, right], 10.0, edges=mesh_edges(quads), metric="geodesic")
    np.testing.assert_allclose(geo, rw, atol=1e-9)               # on a straight strip the metrics agree


def test_geodesic_differs_from_euclidean_across_a_gap():
    """Two lobes close in space but far along the surface: geodesic keeps them apart."""
    v, quads = grid(41, 3)
    v = v.copy()
    # fold the strip into a U: x > 20 goes back over the first half, 2 units above it
    far = v[:, 0] > 20
    v[far, 0] = 40 - v[far, 0]
    v[far, 2] = 2.0
    a, b = np.flatnonzero(np.isclose(v[:, 0], 0) & ~far), np.flatnonzero(np.isclose(v[:, 0], 0) & far)
    eu = region_weights(v, [a, b], 5.0)
    ge = region_weights(v, [a, b], 5.0, edges=mesh_edges(quads), metric="geodesic")
    j = np.flatnonzero(np.isclose(v[:, 0], 2) & ~far)[0]
    assert eu[0, j] < 0.9 and ge[0, j] == 1.0


def test_geodesic_shells_no_group_reaches_use_euclidean_distance():
    v1, q1 = grid(21, 3)
    v2, q2 = grid(3, 3)
    v2 = v2 + [1.0, -5.0, 0.0]                          # a separate shell ("teeth") near x=1..3
    v = np.concatenate([v1, v2])
    quads = q1 + [q + len(v1) for q in q2]
    left, right = np.flatnonzero(v1[:, 0] <= 1), np.flatnonzero(v1[:, 0] >= 19)
    rw = region_weights(v, [left, right], 4.0, edges=mesh_edges(quads), metric="geodesic")
    np.testing.assert_array_equal(rw[0, len(v1):], 1.0)  # the shell follows the region nearest in space


def test_region_blending_is_continuous_across_the_band():
    """Mouth targets lift z, eye targets push z down: the blended surface has no step larger than
    the targets' own neighbour differences plus the linear-ramp share of their difference."""
    v, quads = grid(61, 7, h=0.5)
    left, right = np.flatnonzero(v[:, 0] <= 3), np.flatnonzero(v[:, 0] >= 27)
    rng = np.random.default_rng(5)
    smooth = 0.05 * np.sin(v[:, 0:1] / 5) * np.array([0, 0, 1.0])
    mouth = np.stack([v + (1 + i) * smooth + [0, 0, 2.0] for i in range(3)])
    eyes = np.stack([v - (1 + i) * smooth - [0, 0, 2.0] for i in range(2)])
    ts = TargetSet(["mouth_0", "mouth_1", "mouth_2", "eyes_0", "eyes_1"], list("abcde"),
                   np.concatenate([mouth, eyes]), [None] * 5, v, None)
    band = 6.0
    rt = Retargeter(form="absolute", band=band, metric="euclidean").fit(ts, {"mouth": left, "eyes": right})
    w = rng.uniform(0, 1, size=(20, 5))
    out = rt.transform(w)
    e = mesh_edges(quads)
    step = np.linalg.norm(out[:, e[:, 0]] - out[:, e[:, 1]], axis=-1).max(axis=1)
    per_region = [np.einsum("fk,kvd->fvd", w[:, :3], mouth), np.einsum("fk,kvd->fvd", w[:, 3:], eyes)]
    own = max(np.linalg.norm(p[:, e[:, 0]] - p[:, e[:, 1]], axis=-1).max() for p in per_region)
    gap = np.linalg.norm(per_region[0] - per_region[1], axis=-1).max(axis=1)
    h = 0.5
    assert np.all(step <= own + gap * 2 * h / band + 1e-9)
    mid = np.isclose(v[:, 0], 15.0)          # where the regions meet
    gap_mid = np.linalg.norm(per_region[0] - per_region[1], axis=-1)[:, mid].min(axis=1)
    assert np.all(step < 0.25 * gap_mid)     # a hard switch steps by half the gap twice (midline 0.5/0.5)
    hard = Retargeter(form="absolute", band=1e-6, metric="euclidean").fit(ts, {"mouth": left, "eyes": right}).transform(w)
    hard_step = np.linalg.norm(hard[:, e[:, 0]] - hard[:, e[:, 1]], axis=-1).max(axis=1)
    assert np.all(hard_step > 0.45 * gap_mid)   # the check above can fail


def test_regions_in_one_product_equal_per_region_blends():
    v, _ = grid(11, 3)
    rng = np.random.default_rng(6)
    b = v + rng.normal(scale=0.1, size=(4, len(v), 3))
    ts = TargetSet(["mouth_0", "mouth_1", "eyes_0", "eyes_1"], list("abcd"), b, [None] * 4, None, None)
    g = {"eyes": np.arange(0, 3), "mouth": np.arange(30, 33)}
    rt = Retargeter(band=4.0, metric="euclidean").fit(ts, g)
    w = rng.uniform(0, 1, (9, 4))
    rw = rt.region_weights_
    m, e = rt.region_names_.index("mouth"), rt.region_names_.index("eyes")
    ref = (rw[m][None, :, None] * np.einsum("fk,kvd->fvd", w[:, :2], b[:2])
           + rw[e][None, :, None] * np.einsum("fk,kvd->fvd", w[:, 2:], b[2:]))
    np.testing.assert_allclose(rt.transform(w), ref, atol=1e-12)


@pytest.mark.parametrize("form", ["absolute", "delta"])
@pytest.mark.parametrize("regions", [False, True])
def test_glb_morph_targets_reproduce_the_blend_exactly(form, regions):
    v, _ = grid(9, 4)
    rng = np.random.default_rng(7)
    b = v + rng.normal(scale=0.2, size=(4, len(v), 3))
    ts = TargetSet(["mouth_0", "mouth_1", "eyes_0", "eyes_1"], list("abcd"), b, [None] * 4, v, None)
    rt = Retargeter(form=form, band=3.0, metric="euclidean").fit(
        ts, {"eyes": np.arange(0, 3), "mouth": np.arange(33, 36)} if regions else None)
    w = rng.uniform(0, 1.2, (15, 4))
    base, deltas, names, mw, _ = rt.morph_targets(w)
    glb = base + np.einsum("fk,kvd->fvd", mw, deltas)
    np.testing.assert_allclose(glb, rt.transform(w), atol=1e-12)
    n_extra = (2 if regions else 1) if form == "absolute" else 0
    assert len(names) == 4 + n_extra


def test_clamp_counts_changed_weights():
    v, _ = grid(3, 3)
    ts = TargetSet(["a", "b"], ["a", "b"], np.stack([v, v + 1]), [None] * 2, v, None)
    rt = Retargeter(form="delta").fit(ts)
    w = np.array([[1.2, 0.5], [-0.1, 0.3]])
    assert rt.morph_targets(w, clamp=True)[4] == 2
    np.testing.assert_array_equal(rt.morph_targets(w)[3], w)     # kept by default


def test_unfitted_and_bad_weights():
    with pytest.raises(NotFittedError, match="not fitted"):
        BlendBasis().transform(np.zeros((1, 1)))
    bb = BlendBasis().fit(np.zeros((2, 3, 3)))
    with pytest.raises(InputError, match="nan"):
        bb.transform(np.array([[0.1, np.nan]]))
    with pytest.raises(InputError, match=r"\(n_frames, 2\)"):
        bb.transform(np.zeros((4, 3)))
    with pytest.raises(InputError, match="needs a neutral"):
        BlendBasis("delta").fit(np.zeros((2, 3, 3)))


def _pose(s, th, t, shear=0.0):
    c, si = np.cos(th), np.sin(th)
    m = s[:, None, None] * np.stack([np.stack([c, -si], -1), np.stack([si, c], -1)], -2)
    m[:, 0, 1] += shear
    m[:, 1, 0] += shear
    return np.concatenate([m, t[:, :, None]], axis=2)


def test_similarity_recovers_scale_angle_translation_and_drops_shear():
    rng = np.random.default_rng(8)
    s, th, t = rng.uniform(0.5, 2, 10), rng.uniform(-1, 1, 10), rng.normal(size=(10, 2)) * 50
    s2, th2, t2 = similarity(_pose(s, th, t, shear=0.05))   # symmetric shear: no rotation/scale change
    np.testing.assert_allclose(s2, s, atol=1e-12)
    np.testing.assert_allclose(th2, th, atol=1e-12)
    np.testing.assert_allclose(t2, t)


def test_head_motion_reproduces_the_tracked_image_motion():
    """S_r root(m) + t_r = S_t m + t_t for model points m, with mesh y up and image y down."""
    rng = np.random.default_rng(9)
    n = 12
    s, th, t = rng.uniform(0.8, 1.5, n), rng.uniform(-0.5, 0.5, n), rng.normal(size=(n, 2)) * 30
    pose = _pose(s, th, t)
    hm = head_motion(pose, reference=3)
    m = rng.normal(size=(7, 2))                                # model points (image axes)
    mesh = np.concatenate([m * [1, -1], np.zeros((7, 1))], axis=1)    # y up
    moved = hm.apply(np.broadcast_to(mesh, (n, 7, 3)))
    back = moved[..., :2] * [1, -1]                            # to image axes
    img_ref = np.einsum("ij,fpj->fpi", pose[3, :, :2], back) + pose[3, :, 2][None, None]
    img_t = np.einsum("fij,pj->fpi", pose[:, :, :2], m) + pose[:, None, :, 2]
    np.testing.assert_allclose(img_ref, img_t, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(hm.rotation, axis=1), 1.0)
    np.testing.assert_allclose(hm.scale[3], 1.0)
    np.testing.assert_allclose(hm.translation[3], 0.0, atol=1e-12)


def test_hold_invalid_pose():
    p = np.stack([np.eye(2, 3) * (i + 1) for i in range(4)])
    p[1] = np.nan
    held = hold_invalid(p, np.array([True, True, False, True]))
    np.testing.assert_array_equal(held[[1, 2]], p[[0, 0]])
    with pytest.raises(InputError, match="no frame"):
        hold_invalid(p, np.zeros(4, bool))


def test_identity_with_decompose_weights(tmp_path):
    """Weights written by keyshape decompose (NNLS relative to the mean shape, WEIGHTS.csv with an
    ``interpolated`` column), targets = its 2D key shapes and mean shape: the retargeted frames
    are decompose's own reconstruction (auto form = delta, as the neutral is given)."""
    from keyshape.decompose.weights import nnls_weights, reconstruct
    from keyshape.retarget.targets.target_set import load_targets
    from keyshape.base.formats.weights import read_weights, write_weights
    from keyshape.base.formats.labels import read_pts, write_pts
    rng = np.random.default_rng(11)
    keys = rng.normal(size=(5, 20, 2)) * 5 + 50
    shapes = np.einsum("fk,kpd->fpd", rng.dirichlet(np.ones(5), 30), keys) + rng.normal(scale=0.1, size=(30, 20, 2))
    cols = [f"mouth_{i}" for i in range(5)]
    for c, k in zip(cols, keys):
        write_pts(tmp_path / f"{c}.pts", k)
    write_pts(tmp_path / "neutral.pts", shapes.mean(axis=0))
    keys = np.stack([read_pts(tmp_path / f"{c}.pts") for c in cols])       # as written (3 decimals)
    neutral = read_pts(tmp_path / "neutral.pts")
    w = nnls_weights(shapes, keys, neutral)
    assert np.ptp(w.sum(axis=1)) > 0.01                                      # rows do not sum to one
    write_weights(tmp_path / "w.csv", np.arange(30), cols, w, np.zeros(30))
    frames, names, w_read, _ = read_weights(tmp_path / "w.csv")
    assert names == cols and frames.tolist() == list(range(30))
    rt = Retargeter().fit(load_targets(names, tmp_path))
    assert rt.form_ == "delta"
    np.testing.assert_allclose(rt.transform(w_read), reconstruct(w, keys, neutral), atol=1e-5)
    wrong = Retargeter(form="absolute").fit(load_targets(names, tmp_path)).transform(w_read)
    assert np.abs(wrong - reconstruct(w, keys, neutral)).max() > 1.0     # the other form is visibly off
