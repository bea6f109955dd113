"""Planar bones (001 section 4) and RBF retargeting (001 section 5.1, 002 section 4): properties and errors."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

from keyshape.base.errors import InputError
from keyshape.retarget.mocap.planar_bones import PlanarBones, bone_frames, closest_feature, triangle_min_angles
from keyshape.base.errors import KeyshapeError, NotFittedError
from keyshape.retarget.rbf import RBF


def _surface(seed=0, n_ctrl=30, n_mesh=1500):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n_ctrl, 2))
    ctrl = np.column_stack([xy, 0.2 * np.sin(2 * xy[:, 0])])
    tri = Delaunay(xy).simplices
    tri = tri[triangle_min_angles(ctrl[tri]) > np.deg2rad(5)]  # no hull slivers
    mxy = rng.uniform(-1.1, 1.1, (n_mesh, 2))
    mesh = np.column_stack([mxy, 0.2 * np.sin(2 * mxy[:, 0]) + rng.normal(0, 0.03, n_mesh)])
    return ctrl, tri, mesh, rng


def _rigid(seed):
    return Rotation.random(random_state=seed).as_matrix(), np.array([3.0, -2.0, 5.0]) * (seed + 1)


@pytest.mark.parametrize("unbound", ["still", "nearest", "fade"])
@pytest.mark.parametrize("seed", [0, 1])
def test_planar_zero_motion_and_weights(seed, unbound):
    ctrl, tri, mesh, _ = _surface(seed)
    b = PlanarBones(unbound=unbound).fit(mesh, ctrl, tri)
    np.testing.assert_allclose(b.deform(ctrl), mesh, atol=1e-12)
    w = np.asarray(b.weights.sum(axis=1)).ravel()
    np.testing.assert_allclose(w + b.rest_weight_, 1.0, atol=1e-12)  # bones + rest position sum to one
    if unbound != "fade":
        np.testing.assert_allclose(w[b.bound_], 1.0, atol=1e-12)
    assert np.all(w[~b.bound_] == 0)
    assert np.all(b.pair_weight_ > 0)
    if unbound == "nearest":
        assert b.bound_.all()
    elif unbound == "still":
        assert 0.5 < b.bound_.mean() < 1.0  # the mesh reaches beyond the control surface


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planar_rigid_motion_moves_every_vertex_rigidly(seed):
    ctrl, tri, mesh, _ = _surface(seed)
    b = PlanarBones(unbound="nearest", radius_scale=1.5).fit(mesh, ctrl, tri)
    r, t = _rigid(seed)
    np.testing.assert_allclose(b.deform(ctrl @ r + t), mesh @ r + t, atol=1e-10)
    assert set(np.unique(b.pair_region_)) == set(range(7))  # every region kind exercised


def test_planar_deform_many_matches_deform_and_is_continuous():
    ctrl, tri, mesh, rng = _surface(3)
    b = PlanarBones().fit(mesh, ctrl, tri)
    frames = ctrl + rng.normal(0, 0.05, (7,) + ctrl.shape)
    many = b.deform_many(frames)
    for f in range(7):
        np.testing.assert_allclose(many[f], b.deform(frames[f]), atol=1e-12)
    # continuity across region boundaries: a dense line of vertices moves smoothly
    x = np.linspace(-1.5, 1.5, 6001)
    line = np.column_stack([x, np.full(len(x), 0.1), 0.2 * np.sin(2 * x) + 0.05])  # leaves the surface's reach
    bl = PlanarBones(unbound="fade").fit(line, ctrl, tri)
    assert 0 < bl.rest_weight_.mean() < 1
    disp = bl.deform(frames[0]) - line
    jumps = np.linalg.norm(np.diff(disp, axis=0), axis=1)
    assert jumps.max() < 5e-3, jumps.max()  # displacement ~0.05; no step between neighbours 0.0005 apart
    hard = PlanarBones(unbound="still").fit(line, ctrl, tri).deform(frames[0]) - line
    assert np.linalg.norm(np.diff(hard, axis=0), axis=1).max() > 5e-3  # hard normalisation steps at the edge


def _direct(b, ctrl_frame):
    """Eqs. (1), (9)-(11) pair by pair, without the sparse matrix."""
    fr = bone_frames(ctrl_frame[b.triangles_])[b.pair_bone_, b.pair_region_]      # (n_pairs, 4, 3)
    c = b.pair_coords_
    inplane = c[:, :1] * fr[:, 1] + c[:, 1:2] * fr[:, 2]
    wedge = b.pair_region_ >= 4
    scale = np.where(wedge, b.pair_D_ / np.maximum(np.linalg.norm(inplane, axis=1), 1e-300), 1.0)
    s = fr[:, 0] + scale[:, None] * inplane + c[:, 2:] * fr[:, 3]
    out = b.rest_weight_[:, None] * b.rest_vertices_
    np.add.at(out, b.pair_vertex_, b.pair_weight_[:, None] * s)
    return out


@pytest.mark.parametrize("unbound", ["still", "nearest", "fade"])
def test_planar_sparse_layout_matches_direct_evaluation_with_and_without_threads(unbound):
    ctrl, tri, mesh, rng = _surface(4)
    b = PlanarBones(unbound=unbound, radius_scale=1.5).fit(mesh, ctrl, tri)
    assert (b.pair_region_ >= 4).any()
    frames = ctrl + rng.normal(0, 0.08, (37,) + ctrl.shape)
    direct = np.stack([_direct(b, f) for f in frames])
    for threads in (True, False):
        b.threads = threads
        np.testing.assert_allclose(b.deform_many(frames, chunk=4), direct, atol=1e-12)
        np.testing.assert_allclose(b.deform_many(frames[:5]), direct[:5], atol=1e-12)
        for f in (0, 17, 36):
            np.testing.assert_allclose(b.deform(frames[f]), direct[f], atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_ctrl=st.integers(8, 40), motion=st.floats(0.0, 0.3),
       unbound=st.sampled_from(["still", "nearest", "fade"]), dtype=st.sampled_from(["float64", "float32"]),
       offset=st.floats(-50.0, 50.0), threads=st.booleans())
def test_planar_fast_paths_equal_direct_evaluation_on_random_markers(seed, n_ctrl, motion, unbound, dtype, offset,
                                                                       threads):
    """Property: ``deform`` and ``deform_many`` (the sparse product with its wedge entries refilled per
    frame, eq. 10) equal the pair-by-pair eqs. (1), (9)-(11) on random control surfaces, random
    frames (noise up to 0.3 of a surface of size 2, i.e. large triangle changes) and meshes away
    from the origin: to 1e-12 of the mesh's extent in float64, 1e-6 in float32."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n_ctrl, 2))
    ctrl = np.column_stack([xy, 0.3 * np.sin(2 * xy[:, 0]) * np.cos(xy[:, 1])]) + offset
    tri = Delaunay(xy).simplices
    tri = tri[triangle_min_angles(ctrl[tri]) > np.deg2rad(3)]
    if len(tri) == 0:
        return
    mxy = rng.uniform(-1.2, 1.2, (400, 2))
    mesh = np.column_stack([mxy, 0.3 * np.sin(2 * mxy[:, 0]) * np.cos(mxy[:, 1]) + rng.normal(0, 0.05, 400)]) + offset
    b = PlanarBones(unbound=unbound, radius_scale=rng.uniform(0.5, 2.0), dtype=dtype, threads=threads).fit(mesh, ctrl, tri)
    frames = ctrl + rng.normal(0, motion, (35,) + ctrl.shape)
    direct = np.stack([_direct(b, f) for f in frames])
    scale = np.abs(direct).max()
    tol = (1e-12 if dtype == "float64" else 1e-6) * scale
    many = b.deform_many(frames, chunk=int(rng.integers(1, 20)))
    assert many.dtype == np.dtype(dtype) and np.isfinite(many).all()
    assert np.abs(many - direct).max() <= tol
    for f in (0, 34):
        one = b.deform(frames[f])
        assert one.dtype == np.dtype(dtype)
        assert np.abs(one - direct[f]).max() <= tol


def test_region_partition_matches_eqs_4_5():
    """The nearest-feature partition equals the c_i tests of eqs. (4)-(6) on an acute triangle."""
    tri = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.4, 0.9, 0]])
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 2, (5000, 2)), rng.normal(0, 0.1, 5000)])
    region, dist = closest_feature(pts, np.broadcast_to(tri, (len(pts), 3, 3)))
    fr = bone_frames(tri[None])[0]
    e = np.roll(tri, -1, axis=0) - tri
    elen = np.linalg.norm(e, axis=1)
    c = np.einsum("nij,ij->ni", pts[:, None] - tri, e) / elen            # c_i(S), eq. (6)
    out = np.einsum("nij,ij->ni", pts[:, None] - tri, fr[1:4, 2])         # signed distance beyond edge i
    expect = np.zeros(len(pts), int)
    for i in range(3):
        expect[(out[:, i] > 0) & (c[:, i] >= 0) & (c[:, i] <= elen[i])] = 1 + i
        expect[(c[:, i] < 0) & (c[:, i - 1] > elen[i - 1])] = 4 + i
    np.testing.assert_array_equal(region, expect)
    inside = region == 0
    np.testing.assert_allclose(dist[inside], np.abs(pts[inside, 2]))


def test_masks_keep_masked_vertices_still():
    ctrl, tri, mesh, rng = _surface(4)
    upper = mesh[:, 1] > 0.2
    moving = ctrl[:, 1] < -0.2          # only these markers move
    bone_touches_moving = moving[tri].any(axis=1)
    masks = ~(upper[:, None] & bone_touches_moving[None, :])
    b = PlanarBones().fit(mesh, ctrl, tri, masks=masks)
    moved = ctrl.copy()
    moved[moving] += rng.normal(0, 0.1, (moving.sum(), 3))
    out = b.deform(moved)
    np.testing.assert_allclose(out[upper], mesh[upper], atol=1e-12)
    free = PlanarBones().fit(mesh, ctrl, tri).deform(moved)
    assert np.abs(free[upper] - mesh[upper]).max() > 1e-3  # without the mask they would move


def test_planar_errors():
    ctrl, tri, mesh, _ = _surface(0)
    bad = ctrl.copy()
    bad[tri[0, 2]] = 0.5 * (bad[tri[0, 0]] + bad[tri[0, 1]])
    with pytest.raises(InputError, match="degenerate .*collinear.*bone 0"):
        PlanarBones().fit(mesh, bad, tri)
    with pytest.raises(InputError, match="indices must lie"):
        PlanarBones().fit(mesh, ctrl, tri + 100)
    with pytest.raises(InputError, match="masks"):
        PlanarBones().fit(mesh, ctrl, tri, masks=np.ones((3, 3), bool))
    b = PlanarBones().fit(mesh, ctrl, tri)
    nan = ctrl.copy()
    nan[0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        b.deform(nan)
    with pytest.raises(NotFittedError, match="not fitted"):
        PlanarBones().deform(ctrl)


@pytest.mark.parametrize("kernel", ["imq", "tps", "gaussian"])
def test_rbf_interpolates_centres_and_zero_motion(kernel):
    rng = np.random.default_rng(1)
    u = rng.normal(size=(25, 3))
    v = 1.3 * u + rng.normal(0, 0.1, u.shape)
    f = RBF(kernel).fit(u, v)
    np.testing.assert_allclose(f(u), v, atol=1e-9)
    x = rng.normal(size=(200, 3))
    np.testing.assert_allclose(RBF(kernel).fit(u, u)(x), x, atol=1e-9)
    frames = v + rng.normal(0, 0.1, (4,) + v.shape)
    fm = RBF(kernel).fit(u, frames)
    out = fm(u)
    assert out.shape == (4, 25, 3)
    np.testing.assert_allclose(out, frames, atol=1e-9)
    np.testing.assert_allclose(fm(x)[2], RBF(kernel).fit(u, frames[2])(x), atol=1e-9)


@pytest.mark.parametrize("kernel", ["imq", "tps", "gaussian"])
def test_rbf_affine_term_reproduces_rigid_motion(kernel):
    rng = np.random.default_rng(2)
    u = rng.normal(size=(25, 3))
    r, t = _rigid(2)
    x = 10 * rng.normal(size=(300, 3))  # far from the centres too
    np.testing.assert_allclose(RBF(kernel, affine=True).fit(u, u @ r + t)(x), x @ r + t, atol=1e-8)
    assert np.allclose(RBF("imq").fit(u, u @ r + t).coef_[:25], 0, atol=1e-10)


def test_rbf_imq_radii_are_eq_16():
    rng = np.random.default_rng(3)
    u = rng.normal(size=(10, 3))
    f = RBF("imq").fit(u, u)
    d = np.linalg.norm(u[:, None] - u[None], axis=2) + np.diag(np.full(10, np.inf))
    np.testing.assert_allclose(f.radii_, d.min(axis=1))


def test_rbf_errors():
    rng = np.random.default_rng(4)
    u = rng.normal(size=(10, 3))
    dup = u.copy()
    dup[7] = dup[2]
    with pytest.raises(InputError, match=r"centres 2 \('m2'\) and 7 \('m7'\) coincide"):
        RBF("imq", labels=[f"m{i}" for i in range(10)]).fit(dup, u)
    nan = u.copy()
    nan[3] = np.nan
    with pytest.raises(InputError, match=r"markers \[3\] are NaN"):
        RBF().fit(nan, u)
    with pytest.raises(InputError, match="expected 10 markers"):
        RBF().fit(u, u[:5])
    flat = u.copy()
    flat[:, 2] = 0
    with pytest.raises(InputError, match="plane"):
        RBF("tps").fit(flat, flat)
    with pytest.raises(InputError, match="kernel"):
        RBF("cubic").fit(u, u)
    with pytest.raises(NotFittedError, match="not fitted"):
        RBF()(u)
    err = NotFittedError("x")
    assert isinstance(err, KeyshapeError) and isinstance(err, ValueError)
    with pytest.raises(NotFittedError, match="no target"):
        RBF().fit(u)(u)                                   # factored, but no target to map to


@pytest.mark.parametrize("kernel", ["imq", "gaussian"])
def test_rbf_deform_and_interpolation_matrix_agree_with_fit(kernel):
    """``fit(source).deform(x, target)`` = ``fit(source, target)(x)``; for the Gaussian without the
    affine term (002's face-space deformation), ``x + M (target - source)`` with M the interpolation
    matrix, and with a ridge the keys are only approached (smoothing)."""
    rng = np.random.default_rng(5)
    u = rng.uniform(0, 10, (30, 3))
    frames = u + rng.normal(scale=0.5, size=(3, 30, 3))
    x = rng.uniform(0, 10, (80, 3))
    f = RBF(kernel).fit(u)
    np.testing.assert_allclose(f.deform(x, frames), RBF(kernel).fit(u, frames)(x), atol=1e-9)
    assert not hasattr(f, "coef_")
    if kernel == "gaussian":
        m = f.interpolation_matrix(x)
        np.testing.assert_allclose(f.deform(x, frames[1]), x + m @ (frames[1] - u), atol=1e-9)
        smooth = RBF(kernel, smoothing=0.1).fit(u)
        miss = np.abs(smooth.deform(u, frames[0]) - frames[0]).max()
        assert 1e-3 < miss < np.abs(frames[0] - u).max()
