"""Pose library onto an existing blendshape rig: `keyshape pose`, `retarget --poses --rig` (issue 14)."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from keyshape.base.errors import InputError
from keyshape.base.formats.obj import Mesh, write_obj
from keyshape.base.formats.poses import read_poses, write_rig_landmarks
from keyshape.base.schemes import load_scheme
from keyshape.cli import main
from keyshape.decompose.regions import RegionKeys, region_points
from keyshape.base.geometry import fit_similarity
from keyshape.retarget.rig.poses import (curves_from_library, fit_pose, pose_library, rig_curves)
from keyshape.retarget.api import fit_poses
from keyshape.retarget.rig.model import load_rig, project, shape_regions

SCHEME = load_scheme("contours48")


# ----------------------------------------------------------------------------------------- pure functions

@settings(max_examples=40, deadline=None)
@given(st.floats(0.05, 20), st.floats(-np.pi, np.pi), st.floats(-50, 50), st.floats(-50, 50),
       st.integers(0, 10_000))
def test_fit_similarity_recovers_a_similarity(s, ang, tx, ty, seed):
    """The one similarity fit (keyshape.base.geometry's ``[s R | t]``) gives what the pose library's own (s, R, t)
    fit gave (the Umeyama formula below, as it was in retarget/rig/poses.py), on exact and on noisy points."""
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(12, 2)) * 30
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    exact = s * src @ R.T + [tx, ty]
    np.testing.assert_allclose(fit_similarity(src, exact), np.column_stack([s * R, [tx, ty]]),
                               atol=1e-6 * max(1, s * 100))
    for dst in (exact, exact + rng.normal(size=(12, 2)) * 5 * s):
        A = fit_similarity(src, dst)
        ms, md = src.mean(0), dst.mean(0)
        U, S, Vt = np.linalg.svd((dst - md).T @ (src - ms))
        d = np.sign(np.linalg.det(U @ Vt)) or 1.0
        R0 = U @ np.diag([1.0, d]) @ Vt
        s0 = float((S * [1.0, d]).sum() / ((src - ms) ** 2).sum())
        np.testing.assert_allclose(A[:, :2], s0 * R0, rtol=1e-12, atol=1e-12 * s0)
        np.testing.assert_allclose(A[:, 2], md - s0 * R0 @ ms, rtol=1e-12, atol=1e-9 * max(1, s * 100))
        assert np.linalg.norm(A[:, 0]) == pytest.approx(s0, rel=1e-12)
    with pytest.raises(InputError, match="all equal"):
        fit_similarity(np.ones((4, 2)), src[:4])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_fit_pose_recovers_sparse_bounded_weights(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(40, 12))
    p = np.zeros(12)
    on = rng.choice(12, 3, replace=False)
    p[on] = rng.uniform(0.2, 1.0, 3)
    got = fit_pose(A, A @ p, sparsity=0.0)
    np.testing.assert_allclose(got, p, atol=1e-4)
    # a target beyond the range is met at the bound, never past it
    big = fit_pose(A[:, :1], 3 * A[:, 0], sparsity=0.0)
    assert big[0] == pytest.approx(1.0)


def test_fit_pose_sparsity_prefers_one_strong_shape_and_ignores_free_translation():
    rng = np.random.default_rng(1)
    a = rng.normal(size=20)
    # shape 0 moves the points like shapes 1 + 2 together, at half their weight
    A = np.stack([a, 0.5 * a + 0.01 * rng.normal(size=20), 0.5 * a + 0.01 * rng.normal(size=20)], 1)
    free = np.tile(np.eye(2), (10, 1))
    b = 0.6 * a + free @ [3.0, -2.0]                     # plus a common shift of all points
    p = fit_pose(A, b, sparsity=0.01, free=free)
    assert p[0] > 0.5 and p[1:].max() < 0.05
    assert fit_pose(A, b, sparsity=0.01)[0] < 0.5        # without the free shift the fit is spoiled


def test_rig_curves_is_the_linear_map_of_the_paper():
    rng = np.random.default_rng(0)
    W = rng.uniform(0, 1, (30, 4))
    P = rng.uniform(0, 1, (4, 6))
    pn = rng.uniform(0, 0.2, 6)
    c = rig_curves(W, P, pn, bounds=None)
    for t in (0, 7, 29):                                  # frame = neutral + sum_i w_i (key_i - neutral)
        np.testing.assert_allclose(c[t], pn + sum(W[t, i] * (P[i] - pn) for i in range(4)))
    assert rig_curves(W * 5, P, pn).max() <= 1.0 and rig_curves(-W, P, pn).min() >= 0.0
    with pytest.raises(InputError, match="do not match"):
        rig_curves(W[:, :3], P)


def test_curves_from_library_each_region_drives_only_its_shapes():
    names = ["jawOpen", "mouthSmile_L", "eyeBlink_L", "eyeBlink_R"]
    lib = {"range": [0, 1], "regions": {
        "mouth": {"shapes": ["jawOpen", "mouthSmile_L"], "neutral": {},
                  "keys": {"mouth_0": {"jawOpen": 0.8}, "mouth_1": {"mouthSmile_L": 0.5, "jawOpen": 0.1}}},
        "eyes": {"shapes": ["eyeBlink_L", "eyeBlink_R"], "neutral": {},
                 "keys": {"eyes_0": {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}}}}}
    W = np.array([[1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 0.7]])
    c = curves_from_library(W, ["mouth_0", "mouth_1", "eyes_0"], lib, names)
    np.testing.assert_allclose(c, [[0.8, 0, 0, 0], [0.5, 0.5, 0, 0], [0, 0, 0.7, 0.7]])
    with pytest.raises(InputError, match="no pose"):
        curves_from_library(W, ["mouth_0", "mouth_1", "pupils_0"], lib, names)


# ----------------------------------------------------------------------------------------- a toy rig

SHAPES = {  # contours48 point motions (image axes, y down) of each toy rig shape, per unit weight
    "jawOpen": {p: (0, 6.0) for p in (35, 36, 37, 38, 39, 45, 46, 47)} | {28: (0, 3.0), 34: (0, 3.0)},
    "mouthSmile_L": {34: (4.0, -4.0), 44: (3.0, -3.0), 33: (1.5, -2.0)},
    "mouthSmile_R": {28: (-4.0, -4.0), 40: (-3.0, -3.0), 29: (-1.5, -2.0)},
    "mouthPucker": {28: (4.0, 0), 34: (-4.0, 0), 40: (3.0, 0), 44: (-3.0, 0)},
    "eyeBlink_L": {p: (0, 5.0) for p in (19, 20, 21)},
    "eyeBlink_R": {p: (0, 5.0) for p in (11, 12, 13)},
    "browInnerUp_L": {5: (0, -4.0), 6: (0, -3.0)},
    "browInnerUp_R": {4: (0, -4.0), 3: (0, -3.0)},
    "PupilDilate_L": {},
}


def toy_rig_arrays(shapes: dict = SHAPES):
    """Rig vertices = the 48 contours48 points of a mean face (+ 2 off-face vertices), z = 0."""
    from keyshape.data_synth.face_model import FaceModel
    neutral2d, _ = FaceModel(rng=3).basis()
    neutral2d = np.asarray(neutral2d).reshape(-1, 2)[:48] / 20.0     # rig units ~ cm
    v2d = np.concatenate([neutral2d, [[0, -6], [0, 8]]])
    verts = np.column_stack([v2d[:, 0], -v2d[:, 1], np.zeros(len(v2d))])   # y up in the rig
    deltas = np.zeros((len(shapes), len(verts), 3))
    for j, motion in enumerate(shapes.values()):
        for p, (dx, dy) in motion.items():
            deltas[j, p] = [dx / 20.0, -dy / 20.0, 0.0]
    return verts, deltas


def write_toy_rig(folder, n_bad: int | None = None, shapes: dict = SHAPES):
    verts, deltas = toy_rig_arrays(shapes)
    polys = [np.array([i, i + 1, 48]) for i in range(0, 47)]
    mesh = Mesh(verts, polys)
    folder.mkdir(parents=True, exist_ok=True)
    write_obj(folder / "neutral.obj", mesh)
    for name, d in zip(shapes, deltas):
        write_obj(folder / f"{name}.obj", mesh, verts + d)
    if n_bad is not None:
        write_obj(folder / "broken.obj", Mesh(verts[:n_bad], []))
    lm = folder.parent / "toy_landmarks.json"
    write_rig_landmarks(lm, "contours48", len(verts), list(range(48)))
    return folder, lm


def actor_keys(true_poses: dict[str, dict[str, float]], s=3.0, ang=0.1, shift=(5.0, -2.0)):
    """Keys of an 'actor' whose face is the toy rig seen through a similarity: rest + S (rig pose motion)."""
    verts, deltas = toy_rig_arrays()
    names = list(SHAPES)
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    to_actor = lambda p2: s * p2 @ R.T + shift  # noqa: E731
    rest = to_actor(project(verts[:48]))
    regions = []
    for region in ("mouth", "eyes"):
        idx = region_points(SCHEME, region)
        keys = []
        knames = [k for k in true_poses if k.startswith(region)]
        for k in knames:
            c = np.zeros(len(names))
            for n, v in true_poses[k].items():
                c[names.index(n)] = v
            keys.append(to_actor(project(verts[:48] + np.tensordot(c, deltas[:, :48], 1)))[idx])
        regions.append(RegionKeys(region, "greedy", idx, np.arange(len(keys)), np.array(keys), rest[idx],
                                  None, rest[idx], 0))
    return regions


TRUE = {"mouth_0": {"jawOpen": 0.7}, "mouth_1": {"mouthSmile_L": 0.6, "mouthSmile_R": 0.5},
        "mouth_2": {"mouthPucker": 0.8, "jawOpen": 0.2}, "eyes_0": {"eyeBlink_L": 1.0, "eyeBlink_R": 0.9},
        "eyes_1": {"browInnerUp_L": 0.5, "browInnerUp_R": 0.5}}


def test_pose_library_recovers_the_poses_of_keys_made_from_the_rig():
    verts, deltas = toy_rig_arrays()
    ld = project(deltas[:, :48])
    groups = {r: region_points(SCHEME, r) for r in ("mouth", "eyes", "pupils")}
    rs = shape_regions(ld, groups, names=list(SHAPES))
    names = list(SHAPES)
    assert [names[j] for j in rs["mouth"]] == ["jawOpen", "mouthSmile_L", "mouthSmile_R", "mouthPucker"]
    assert "PupilDilate_L" not in [names[j] for r in rs.values() for j in r]        # moves nothing
    # with the priors near zero (sparsity 0.001, no left-right prior) the fit is exact
    lib = pose_library(actor_keys(TRUE), names, project(verts[:48]), ld, rs, sparsity=0.001, nuisance="none",
                       symmetry=0.0)
    fit = lib.pop("_fit")
    for k, pose in TRUE.items():
        region = k.split("_")[0]
        got = lib[region]["keys"][k]
        for n in names:
            assert got.get(n, 0.0) == pytest.approx(pose.get(n, 0.0), abs=0.01), (k, n, got)
        assert fit[k] < 0.01


def test_pose_reads_the_rig_in_the_frame_the_keys_were_stabilised_in(tmp_path):
    """A rig blink that also lowers its eye's corners (ICT-FaceKit's does), and the actor's blink key
    stabilised on the eye corners (``select --head-pose rigid``), which therefore never shows the corners
    move: ``pose`` reads the rig's motion in that same frame (the rigid points' mean height held,
    :func:`~keyshape.retarget.rig.solve.rigid_frame_deltas`, as ``solve`` does) and gets the blink whole. Read
    in the rig's own frame, the key's corners held still took the brows down with them: eyeBlink_L 0.66
    and browInnerUp 0.17 on both sides, residual 39%."""
    from keyshape.retarget.api import fit_poses
    shapes = dict(SHAPES)
    shapes["eyeBlink_L"] = {p: (0, 5.0) for p in (19, 20, 21)} | {18: (0, 1.5), 22: (0, 1.5)}
    folder, lm = write_toy_rig(tmp_path / "rig", shapes=shapes)
    rig = load_rig(folder, with_mesh=False)
    verts, deltas = toy_rig_arrays(shapes)
    rest = project(verts[:48])
    key = project(verts[:48] + 0.8 * deltas[list(shapes).index("eyeBlink_L"), :48])
    rigid = list(SCHEME.rigid)
    key = key - (key - rest)[rigid].mean(axis=0)             # the stabiliser holds the corners' mean still
    idx = region_points(SCHEME, "eyes")
    regions = [RegionKeys("eyes", "greedy", idx, np.arange(1), key[idx][None], rest[idx], None, rest[idx], 0)]
    lib, fit = fit_poses(regions, "contours48", rig, {"method": "rigid", "points": rigid}, lm, sparsity=0.001,
                         symmetry=0.0)
    assert lib["regions"]["eyes"]["keys"]["eyes_0"] == pytest.approx({"eyeBlink_L": 0.8}, abs=0.01)
    assert fit["eyes_0"] < 0.01


def test_pose_and_retarget_commands_end_to_end(tmp_path):
    from keyshape.base.formats.keys import write_keys
    from keyshape.base.formats.weights import read_weights
    from keyshape.base.formats.weights import write_weights as write_key_weights
    rig, lm = write_toy_rig(tmp_path / "rig")
    write_keys(tmp_path / "keys.json", "contours48", 48, actor_keys(TRUE))
    assert main(["pose", str(tmp_path / "keys.json"), "--rig", str(rig), "--landmarks", str(lm),
                 "-o", str(tmp_path / "poses.json")]) == 0
    poses = read_poses(tmp_path / "poses.json", list(SHAPES))
    assert poses["regions"]["mouth"]["keys"]["mouth_0"]["jawOpen"] == pytest.approx(0.7, abs=0.03)
    cols = list(TRUE)
    W = np.zeros((5, len(cols)))
    W[np.arange(5), np.arange(5)] = [1.0, 0.5, 1.0, 0.25, 3.0]
    write_key_weights(tmp_path / "w.csv", np.arange(5), cols, W)
    assert main(["retarget", str(tmp_path / "w.csv"), "--poses", str(tmp_path / "poses.json"), "--rig", str(rig),
                 "-o", str(tmp_path / "curves.csv")]) == 0
    frames, names, C, _ = read_weights(tmp_path / "curves.csv")
    assert set(names) == set(SHAPES)
    col = {n: i for i, n in enumerate(names)}
    assert C[0, col["jawOpen"]] == pytest.approx(0.7, abs=0.03)
    assert C[3, col["eyeBlink_L"]] == pytest.approx(0.25, abs=0.02)
    assert C[4, col["browInnerUp_L"]] == pytest.approx(1.0, abs=1e-6)         # 3 x 0.5: clipped to the range
    assert C[:, col["PupilDilate_L"]].max() == 0
    assert main(["retarget", str(tmp_path / "w.csv"), "--poses", str(tmp_path / "poses.json"), "--rig", str(rig),
                 "--livelink", "-o", str(tmp_path / "ll.csv")]) == 0
    header = (tmp_path / "ll.csv").read_text().splitlines()[0].split(",")
    assert header[:3] == ["Timecode", "BlendShapeCount", "EyeBlinkLeft"]
    assert main(["retarget", str(tmp_path / "w.csv"), "--poses", str(tmp_path / "poses.json"), "--rig", str(rig),
                 "-o", str(tmp_path / "take.glb")]) == 0
    import pygltflib
    g = pygltflib.GLTF2().load(str(tmp_path / "take.glb"))
    # only the shapes that move in the take are morph targets (PupilDilate_L stays at 0 throughout)
    moving = [n for n in load_rig(rig).names if np.abs(C[:, col[n]]).max() > 0]
    assert "PupilDilate_L" not in moving and len(moving) >= 8
    assert g.meshes[0].extras["targetNames"] == moving
    assert len(g.meshes[0].primitives[0].targets) == len(moving)


# ----------------------------------------------------------------------------------------- bad input

def _setup(tmp_path):
    from keyshape.base.formats.keys import write_keys
    rig, lm = write_toy_rig(tmp_path / "rig")
    write_keys(tmp_path / "keys.json", "contours48", 48, actor_keys(TRUE))
    assert main(["pose", str(tmp_path / "keys.json"), "--rig", str(rig), "--landmarks", str(lm),
                 "-o", str(tmp_path / "poses.json")]) == 0
    from keyshape.base.formats.weights import write_weights as write_key_weights
    write_key_weights(tmp_path / "w.csv", np.arange(3), list(TRUE), np.full((3, len(TRUE)), 0.5))
    return rig, lm


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["regions"]["mouth"]["keys"]["mouth_0"].update({"tongueOut": 0.5}), "tongueOut"),
    (lambda d: d["regions"]["mouth"]["shapes"].append("cheekPuff"), "lacks"),
    (lambda d: d["regions"]["mouth"]["keys"]["mouth_0"].update({"jawOpen": 1.7}), "outside the rig's range"),
    (lambda d: d["regions"]["eyes"]["keys"]["eyes_0"].update({"eyeBlink_L": -0.2}), "outside the rig's range"),
    (lambda d: d["regions"]["eyes"]["keys"]["eyes_0"].update({"eyeBlink_L": "x"}), "not a finite number"),
])
def test_bad_poses_file_is_refused_naming_it_and_nothing_written(tmp_path, capsys, edit, message):
    rig, _ = _setup(tmp_path)
    p = tmp_path / "poses.json"
    d = json.loads(p.read_text())
    edit(d)
    p.write_text(json.dumps(d))
    out = tmp_path / "curves.csv"
    assert main(["retarget", str(tmp_path / "w.csv"), "--poses", str(p), "--rig", str(rig), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(p) in err and message in err
    assert not out.exists()


def test_rig_with_a_shape_of_another_vertex_count_is_refused(tmp_path, capsys):
    rig, lm = write_toy_rig(tmp_path / "rig", n_bad=20)
    with pytest.raises(InputError, match="broken.obj.*20 vertices"):
        load_rig(rig)
    from keyshape.base.formats.keys import write_keys
    write_keys(tmp_path / "keys.json", "contours48", 48, actor_keys(TRUE))
    out = tmp_path / "poses.json"
    assert main(["pose", str(tmp_path / "keys.json"), "--rig", str(rig), "--landmarks", str(lm),
                 "-o", str(out)]) == 2
    assert "broken.obj" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("option, value, message", [
    ("opposed", 0.5, "--opposed 0.5: a cosine from -1 to 0"),
    ("opposed", float("nan"), "--opposed nan: a cosine from -1 to 0"),
    ("sparsity", -1.0, "--sparsity -1.0: a number from 0 to 100"),
    ("sparsity", float("inf"), "--sparsity inf: a number from 0 to 100"),
    ("symmetry", -1.0, "--symmetry -1.0: a number from 0 to 100"),
])
def test_pose_options_out_of_range_are_refused_before_the_fit(tmp_path, option, value, message):
    rig, lm = write_toy_rig(tmp_path / "rig")
    with pytest.raises(InputError, match=re.escape(message)):
        fit_poses(actor_keys(TRUE), "contours48", load_rig(rig), None, lm, **{option: value})


def test_rig_without_landmarks_asks_for_them(tmp_path, capsys):
    """No correspondence and no blink shapes to find one by (retarget/rig/landmarks.py): one line asks for
    --landmarks and says what was missing."""
    from keyshape.base.formats.keys import write_keys
    rig, _ = write_toy_rig(tmp_path / "rig", shapes={k: v for k, v in SHAPES.items() if not k.startswith("eyeBlink")})
    write_keys(tmp_path / "keys.json", "contours48", 48, actor_keys(TRUE))
    assert main(["pose", str(tmp_path / "keys.json"), "--rig", str(rig), "-o", str(tmp_path / "p.json")]) == 2
    err = capsys.readouterr().err
    assert "--landmarks" in err and "eyeBlinkLeft (eyeBlink_L)" in err and len(err.strip().splitlines()) == 1


# ----------------------------------------------------------------------------------------- a .glb that opens right

def test_rig_glb_has_normals_materials_frame_range_and_passes_validator(tmp_path):
    import pygltflib

    from keyshape.base.geometry import vertex_normals
    from keyshape.retarget.rig.model import Rig
    from keyshape.retarget.output.rig_export import export_rig
    verts, deltas = toy_rig_arrays()
    polys = [np.array([i, i + 1, 48]) for i in range(0, 47)] + [np.array([0, 49, 47, 10])]
    mesh = Mesh(verts, polys, materials={"M_Face": np.arange(0, 30), "M_Teeth": np.arange(30, 48)})
    rig = Rig(list(SHAPES), verts, deltas, mesh)
    curves = np.random.default_rng(0).uniform(0, 1, (12, len(SHAPES)))
    out = tmp_path / "take.glb"
    export_rig(out, rig, np.arange(100, 112), curves, fps=24.0)
    g = pygltflib.GLTF2().load(str(out))
    prims = g.meshes[0].primitives
    assert [g.materials[p.material].name for p in prims] == ["M_Face", "M_Teeth"]
    assert g.materials[1].pbrMetallicRoughness.baseColorFactor[:3] == pytest.approx([0.92, 0.9, 0.84])
    assert prims[0].attributes.NORMAL is not None and "NORMAL" in prims[0].targets[0]
    assert g.scenes[0].extras == {"fps": 24.0, "frame_start": 100, "frame_end": 111}
    times = g.accessors[g.animations[0].samplers[0].input]
    assert times.min[0] == pytest.approx(100 / 24) and times.max[0] == pytest.approx(111 / 24)
    # morph targets are stored sparse (only the vertices each shape moves) and read back as the rig's deltas
    blob = g.binary_blob()
    ids = np.arange(len(verts))                      # no UVs: one glTF vertex per rig vertex

    def accessor_values(i):
        acc = g.accessors[i]
        out = np.zeros((acc.count, 3), np.float32)
        if acc.bufferView is not None:
            bv = g.bufferViews[acc.bufferView]
            out[:] = np.frombuffer(blob, np.float32, acc.count * 3, bv.byteOffset).reshape(-1, 3)
        if acc.sparse is not None:
            bi, bv = g.bufferViews[acc.sparse.indices.bufferView], g.bufferViews[acc.sparse.values.bufferView]
            idx = np.frombuffer(blob, np.uint32, acc.sparse.count, bi.byteOffset)
            out[idx] = np.frombuffer(blob, np.float32, acc.sparse.count * 3, bv.byteOffset).reshape(-1, 3)
        return out

    assert any(g.accessors[t["POSITION"]].sparse is not None for t in prims[0].targets)
    for j, t in enumerate(prims[0].targets):
        np.testing.assert_allclose(accessor_values(t["POSITION"]), deltas[j][ids], rtol=0, atol=1e-6)
    # the normal deltas are the change of the normals: base + delta = normals of the shape
    n0 = vertex_normals(verts, mesh.triangles)
    assert np.allclose(np.linalg.norm(n0, axis=1), 1)
    try:
        from tests.test_retarget_io import run_validator
    except ImportError:                                   # tests not importable as a package
        import importlib.util
        import pathlib
        spec = importlib.util.spec_from_file_location("tri", pathlib.Path(__file__).parent / "test_retarget_io.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        run_validator = mod.run_validator
    rep = run_validator(out, tmp_path)
    assert rep["errors"] == 0 and rep["warnings"] == 0, rep


# ----------------------------------------------------------------------------------------- preview

def _preview_inputs(tmp_path, n: int, size: tuple[int, int]):
    """The toy rig, ``n`` frames of toy tracks (t.csv), a grey ramp video of ``size`` (v.mp4) and curves
    opening the rig's first shape from 0 to 1 (c.csv) in ``tmp_path``; returns the rig folder and curves."""
    from keyshape.base.formats.tracks import write_tracks
    from keyshape.base.formats.video import video_writer
    from keyshape.base.formats.weights import write_weights
    from toy import toy_tracks
    rig, _ = write_toy_rig(tmp_path / "rig")
    write_tracks(tmp_path / "t.csv", toy_tracks(n, rng=1))
    with video_writer(tmp_path / "v.mp4", 10, size) as wr:
        for i in range(n):
            wr.write(np.full((size[1], size[0], 3), 8 * i, np.uint8))
    c = np.zeros((n, len(SHAPES)))
    c[:, 0] = np.linspace(0, 1, n)
    write_weights(tmp_path / "c.csv", np.arange(n), list(SHAPES), c)
    return rig, c


def test_preview_renders_range_and_sheet(tmp_path):
    from keyshape.base.formats.video import video_info
    rig, _ = _preview_inputs(tmp_path, 30, (160, 120))
    out, sheet = tmp_path / "p.mp4", tmp_path / "s.jpg"
    assert main(["preview", str(tmp_path / "v.mp4"), "--tracks", str(tmp_path / "t.csv"), "--curves",
                 str(tmp_path / "c.csv"), "--rig", str(rig), "--frames", "5:17", "--sheet", str(sheet),
                 "-o", str(out)]) == 0
    info = video_info(out)
    assert info.n_frames == 12 and info.height == 120 and info.width > 2 * 120
    import cv2
    assert cv2.imread(str(sheet)) is not None
    assert main(["preview", str(tmp_path / "v.mp4"), "--tracks", str(tmp_path / "t.csv"), "--curves",
                 str(tmp_path / "c.csv"), "--rig", str(rig), "--frames", "40:50", "-o",
                 str(tmp_path / "q.mp4")]) == 2
    assert not (tmp_path / "q.mp4").exists()


def test_rig_renderer_draws_the_face_and_moves_with_the_curves(tmp_path):
    from keyshape.retarget.output.preview import RigRenderer
    from keyshape.retarget.rig.model import Rig
    # a square of two triangles facing the camera, one shape moving it right
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    d = np.zeros((1, 4, 3))
    d[0, :, 0] = 1.0
    rig = Rig(["right"], v, d, Mesh(v, [np.array([0, 1, 2, 3])]))
    r = RigRenderer(rig, size=(64, 64), background=(0, 0, 0)).fit(np.array([[0.0], [1.0]]))
    a = r.render(rig.evaluate(np.array([[0.0]]))[0]).sum(axis=2) > 0
    b = r.render(rig.evaluate(np.array([[1.0]]))[0]).sum(axis=2) > 0
    assert 0.15 < a.mean() < 0.5 and abs(a.mean() - b.mean()) < 0.05
    cols_a, cols_b = np.flatnonzero(a.any(0)), np.flatnonzero(b.any(0))
    assert cols_b.mean() > cols_a.mean() + 10                       # moved to the image-right
    back = Rig(["right"], v, d, Mesh(v, [np.array([3, 2, 1, 0])]))   # facing away: culled
    rb = RigRenderer(back, size=(64, 64), background=(0, 0, 0)).fit(None)
    assert rb.render(v).sum() == 0


def test_threaded_rendering_gives_the_same_frames_in_order(tmp_path):
    from keyshape.retarget.output.preview import RigRenderer, ordered_map
    rig, _ = write_toy_rig(tmp_path / "rig")
    from keyshape.retarget.rig.model import load_rig
    rig = load_rig(rig)
    curves = np.random.default_rng(3).uniform(0, 1, (23, rig.n_shapes))
    r = RigRenderer(rig, size=(96, 96)).fit(curves)
    one = list(r.render_many(curves, workers=1))
    three = list(r.render_many(curves, workers=3))
    assert len(one) == len(three) == 23
    for a, b in zip(one, three):
        np.testing.assert_array_equal(a, b)
    assert len({a.tobytes() for a in one}) > 10                      # the frames differ: order is tested
    # tags come back in submission order even when late jobs finish first
    import time
    out = list(ordered_map(lambda x: (time.sleep(0.02 * (5 - x)), x)[1], ((i, i % 5) for i in range(12)), 4))
    assert [t for t, _, _ in out] == list(range(12)) and [y for _, y, _ in out] == [i % 5 for i in range(12)]


def test_support_regions_from_the_targets_themselves(tmp_path):
    from keyshape.retarget.rig.model import support_regions
    verts, deltas = toy_rig_arrays()
    names = list(SHAPES)
    cols = ["mouth_0", "mouth_1", "eyes_0", "eyes_1"]
    shapes = verts + deltas[[names.index("jawOpen"), names.index("mouthSmile_L"), names.index("eyeBlink_L"),
                             names.index("browInnerUp_L")]]
    reg = support_regions(shapes, verts, cols)
    mouth, eyes = set(region_points(SCHEME, "mouth").tolist()), set(region_points(SCHEME, "eyes").tolist())
    assert set(reg["mouth"].tolist()) <= mouth and set(reg["eyes"].tolist()) <= eyes
    assert {34, 45}.issubset(set(reg["mouth"].tolist())) and {5, 19}.issubset(set(reg["eyes"].tolist()))
    with pytest.raises(InputError, match="move no vertex"):
        support_regions(np.stack([shapes[0], verts]), verts, ["mouth_0", "eyes_0"])
    # the command: --regions auto blends each region's targets on its own vertices
    from keyshape.base.formats.weights import write_weights
    tdir = tmp_path / "t"
    tdir.mkdir()
    mesh = Mesh(verts, [np.array([i, i + 1, 48]) for i in range(0, 47)])
    write_obj(tdir / "neutral.obj", mesh)
    for c, sh in zip(cols, shapes):
        write_obj(tdir / f"{c}.obj", mesh, sh)
    write_weights(tmp_path / "w.csv", np.arange(2), cols, np.array([[1.0, 0, 1.0, 0], [0, 0, 0, 0]]))
    assert main(["retarget", str(tmp_path / "w.csv"), "--targets", str(tdir), "--regions", "auto",
                 "-o", str(tmp_path / "f")]) == 0
    from keyshape.base.formats.obj import read_obj_vertices
    v = read_obj_vertices(tmp_path / "f" / "frame_000000.obj")
    np.testing.assert_allclose(v[37], shapes[0][37], atol=1e-5)          # jaw moved the lower lip
    np.testing.assert_allclose(v[20], shapes[2][20], atol=1e-5)          # blink moved the upper lid


# ------------------------------------------------------------------ synthetic face vs rig: amplitude diagnostic

def test_component_gains_against_a_rig_made_from_the_face_itself():
    """A rig whose shapes are the synthetic face's own component motions, seen through a known
    similarity and driven at known amplitudes, gives back those amplitudes (gain = 1 / amplitude)
    with cosine 1; an unsided component split over _L/_R shapes counts both sides."""
    from keyshape.data_synth.face_model import COMPONENTS, FaceModel
    from rig_truth import component_gains
    neutral, basis = FaceModel(rng=5).basis()
    ang, s, t = 0.3, 0.07, np.array([2.0, -1.0])
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    amp = np.linspace(0.5, 2.5, len(COMPONENTS))                  # rig shape k moves amp_k x the component
    names, deltas = [], []
    for k, c in enumerate(COMPONENTS):
        d = amp[k] * basis[k] @ (s * R).T
        if c == "browInnerUp":                                    # the rig splits it into sides
            left = np.zeros_like(d)
            left[5:10] = d[5:10]
            names += ["browInnerUp_L", "browInnerUp_R"]
            deltas += [left, d - left]
        else:
            names.append(c)
            deltas.append(d)
    gains, cos = component_gains(neutral, basis, COMPONENTS, names, neutral @ (s * R).T + t, np.stack(deltas))
    np.testing.assert_allclose(gains, 1.0 / amp, rtol=1e-9)
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)
    # a rig shape that moves the points another way: cosine below 1, gain its least-squares amplitude
    other = np.stack(deltas).copy()
    other[0] = np.roll(other[0], 3, axis=0)
    g2, c2 = component_gains(neutral, basis, COMPONENTS, names, neutral @ (s * R).T + t, other)
    assert c2[0] < 0.9 and abs(g2[0] - 1.0 / amp[0]) > 0.05
    with pytest.raises(InputError, match="no landmark motion"):
        component_gains(neutral, basis, COMPONENTS, names, neutral @ (s * R).T + t, np.zeros_like(other))


# ----------------------------------------------------------------------------------------- antagonists

def test_opposed_shapes_are_never_used_together_and_the_better_one_stays():
    """Two shapes that cancel in the points (a raise and a lowering of one brow) plus one that makes the
    rest of the key: without the rule the fit mixes both opposed shapes to shape the key; with it one goes,
    the one whose loss costs the fit least, and the free fit of the other shapes absorbs the rest."""
    from keyshape.retarget.rig.poses import opposed_pairs
    rng = np.random.default_rng(3)
    up = rng.normal(size=30)
    down = -up + 0.4 * rng.normal(size=30)            # mostly the opposite motion, partly its own shape
    other = rng.normal(size=30)
    A = np.stack([up, down, other], axis=1)
    assert opposed_pairs(A) == [(0, 1)]
    assert opposed_pairs(A, cosine=-0.99) == []
    b = A @ [0.8, 0.5, 0.3]                           # a key made of both: 2D-consistent, 3D nonsense
    free_fit = fit_pose(A, b, sparsity=0.0)
    assert free_fit[0] > 0.1 and free_fit[1] > 0.1
    excl = fit_pose(A, b, sparsity=0.0, exclusive=[(0, 1)])
    assert (excl[:2] > 0).sum() == 1
    # the kept one is the one that explains the key better alone
    res = [np.linalg.norm(A @ fit_pose(A, b, sparsity=0.0, exclusive=[(0, 1)]) - b)]
    for drop in (0, 1):
        keep = [j for j in range(3) if j != drop]
        p = np.zeros(3)
        p[keep] = fit_pose(A[:, keep], b, sparsity=0.0)
        res.append(np.linalg.norm(A @ p - b))
    assert res[0] == pytest.approx(min(res[1:]), rel=1e-6)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_exclusive_pairs_hold_on_random_problems(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(24, 8))
    A[:, 1] = -A[:, 0] + 0.3 * rng.normal(size=24)
    A[:, 3] = -A[:, 2] + 0.3 * rng.normal(size=24)
    b = A @ rng.uniform(0, 1, 8)
    pairs = [(0, 1), (2, 3)]
    p = fit_pose(A, b, sparsity=0.01, exclusive=pairs)
    assert all(not (p[i] > 0 and p[j] > 0) for i, j in pairs)
    assert ((p >= 0) & (p <= 1)).all()


def test_left_right_prior_evens_a_symmetric_key_and_keeps_a_one_sided_one():
    """The left-right prior (``pose --symmetry``): two mirrored shapes of which each also makes a little
    of the other side's motion. A key made of both, read a little stronger on one side, is fitted more
    evenly than it reads; a one-sided key stays one-sided (within 5%); mirror-image keys get
    mirror-image poses."""
    rng = np.random.default_rng(5)
    side, both = rng.normal(size=20), rng.normal(size=20)
    L = np.concatenate([side, 0.3 * side])                        # the left shape, some motion on the right
    R = np.concatenate([0.3 * side, side])                        # its mirror image
    shared = np.concatenate([both, both])                         # a third shape: both sides at once
    A = np.stack([L, R, shared], axis=1)
    mirrored = [(0, 1)]
    b = A @ [0.55, 0.45, 0.0]                 # an even key read a little stronger on one side
    free = fit_pose(A, b, sparsity=0.0)
    even = fit_pose(A, b, sparsity=0.0, symmetry=0.03, mirrored=mirrored)
    assert free[0] - free[1] == pytest.approx(0.1, abs=1e-4)
    assert 0.06 < even[0] - even[1] < 0.095 and even[:2].sum() == pytest.approx(1.0, abs=0.02)
    one = fit_pose(A, A @ [0.6, 0.0, 0.0], sparsity=0.01, symmetry=0.03, mirrored=mirrored)
    assert one[0] == pytest.approx(0.6, abs=0.05) and one[1] < 0.05
    other = fit_pose(A, A @ [0.0, 0.6, 0.0], sparsity=0.01, symmetry=0.03, mirrored=mirrored)
    np.testing.assert_allclose(other[[1, 0, 2]], one, atol=1e-4)
    assert fit_pose(A, A @ [0.6, 0.0, 0.0], sparsity=0.01)[0] == pytest.approx(0.6, abs=0.02)


def test_a_sideways_pair_stays_opposed_under_a_free_translation():
    """mouthLeft and mouthRight move the lips mostly sideways, against each other; with the mouth's
    translation free that part is projected out and what is left of the two (each narrows the lips a
    little) no longer opposes, so both at once would make a narrowing: a mirrored pair opposed by its
    motions before the nuisances are projected out stays opposed."""
    from keyshape.retarget.rig.poses import nuisance_motions, opposed_pairs
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(12, 2))
    narrow = (-pts * [1.0, 0.0]).ravel()                        # corners in
    side = np.tile([1.0, 0.0], 12)
    A = np.stack([side + 0.3 * narrow, -side + 0.3 * narrow, narrow], axis=1)
    F = nuisance_motions(pts, "translation")
    assert opposed_pairs(A) == [(0, 1)]
    assert opposed_pairs(A, F) == []
    assert opposed_pairs(A, F, mirrored=[(1, 0)]) == [(0, 1)]
    assert opposed_pairs(A, F, mirrored=[(0, 2)]) == []         # a mirrored pair that does not oppose
    b = A @ [0.0, 0.0, 0.6]
    both = fit_pose(A[:, :2], b, sparsity=0.0, free=F)
    assert (both > 0.1).all()                                   # the two together fake the narrowing
    p = fit_pose(A, b, sparsity=0.01, free=F, exclusive=opposed_pairs(A, F, mirrored=[(0, 1)]))
    assert not (p[0] > 0 and p[1] > 0) and p[2] == pytest.approx(0.6, abs=0.05)


def test_ict_antagonists_and_eye_shapes_of_the_real_rig(shared_data):
    """On ICT-FaceKit: browDown/browOuterUp and mouthLeft/mouthRight are opposed pairs; eyeWide,
    eyeSquint and cheekSquint drive the eyes (a third of eyeBlink's lid motion, far below jawOpen's);
    jawForward, invisible from the front, drives nothing."""
    from keyshape.retarget.rig.poses import landmark_motion, opposed_pairs
    from keyshape.retarget.rig.model import rig_landmarks
    from keyshape.decompose.regions import available_regions, region_points
    rig = load_rig(shared_data / "ict-facekit", with_mesh=False)
    W, _ = rig_landmarks(rig, "contours48")
    ld = project(np.einsum("pv,svc->spc", W, rig.deltas, optimize=True))
    groups = {r: region_points(SCHEME, r) for r in available_regions(SCHEME)}
    rs = shape_regions(ld, groups, names=rig.names)
    eyes = [rig.names[j] for j in rs["eyes"]]
    for n in ("eyeWide_L", "eyeSquint_R", "cheekSquint_L", "eyeBlink_L", "browDown_R"):
        assert n in eyes
    assert "jawForward" not in [rig.names[j] for r in rs.values() for j in r]
    for region, a, b in (("eyes", "browDown_L", "browOuterUp_L"), ("mouth", "mouthLeft", "mouthRight")):
        idx = list(rs[region])
        pairs = opposed_pairs(landmark_motion(ld[idx], groups[region]))
        names = {(rig.names[idx[i]], rig.names[idx[j]]) for i, j in pairs}
        assert (a, b) in names or (b, a) in names, (region, sorted(names)[:10])


def test_preview_compare_panel_crop_and_head_turn(tmp_path):
    """--compare adds a third panel; the face crop is a steady square around the tracked points; head
    angles in the curves turn the rendered rig (yaw > 0: the face turns to the subject's left, image-right;
    the conventions of retarget's head columns)."""
    from keyshape.base.formats.video import video_info
    from keyshape.base.formats.weights import write_weights
    from keyshape.retarget.output.preview import face_crop, head_rotations
    rig, c = _preview_inputs(tmp_path, 20, (320, 240))
    write_weights(tmp_path / "m.csv", np.arange(20), list(SHAPES), c[::-1])
    base = ["preview", str(tmp_path / "v.mp4"), "--tracks", str(tmp_path / "t.csv"), "--curves",
            str(tmp_path / "c.csv"), "--rig", str(rig), "--size", "100"]
    assert main(base + ["-o", str(tmp_path / "two.mp4")]) == 0
    assert main(base + ["--compare", str(tmp_path / "m.csv"), "-o", str(tmp_path / "three.mp4")]) == 0
    w2, w3 = video_info(tmp_path / "two.mp4").width, video_info(tmp_path / "three.mp4").width
    assert w2 == 2 * 100 + 4 and w3 == 3 * 100 + 8               # square face crop: every panel 100 x 100
    write_weights(tmp_path / "short.csv", np.arange(10), list(SHAPES), c[:10])
    assert main(base + ["--compare", str(tmp_path / "short.csv"), "-o", str(tmp_path / "x.mp4")]) == 2
    assert not (tmp_path / "x.mp4").exists()
    # the crop holds every tracked point of the range and stays inside the image
    rng = np.random.default_rng(2)
    P = np.array([150, 110]) + rng.normal(0, 1, (20, 1, 2)) * 5 + rng.uniform(-30, 30, (1, 48, 2))
    x0, y0, side = face_crop(P, np.ones(20, bool), (320, 240))
    assert 0 <= x0 and 0 <= y0 and x0 + side <= 320 and y0 + side <= 240
    assert (P[..., 0] >= x0).all() and (P[..., 0] <= x0 + side).all()
    assert (P[..., 1] >= y0).all() and (P[..., 1] <= y0 + side).all()
    # head angles: rotations, and their directions in the rig's frame (x: subject's left, y: up, z: to camera)
    R = head_rotations(["headYaw", "headPitch", "headRoll"], np.array([[30.0, 0, 0], [0, 20.0, 0], [0, 0, 10.0]]))
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3))
    nose = np.array([0.0, 0.0, 1.0])
    assert (R[0] @ nose)[0] == pytest.approx(np.sin(np.radians(30)))   # yaw: nose to the subject's left
    assert (R[1] @ nose)[1] == pytest.approx(-np.sin(np.radians(20)))  # pitch: nose down
    assert (R[2] @ np.array([0, 1.0, 0]))[0] == pytest.approx(-np.sin(np.radians(10)))  # roll: top to the right
    assert head_rotations(["jawOpen"], np.zeros((2, 1))) is None


def test_rig_renderer_turns_with_the_head(tmp_path):
    from keyshape.retarget.output.preview import RigRenderer, head_rotations
    from keyshape.retarget.rig.model import Rig
    # a box's front face and a side face: a yaw towards +x shows less of the front and more of the side
    v = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1], [1, 0, 1], [1, 0, 0], [1, 1, 0], [1, 1, 1]], float)
    rig = Rig(["none"], v, np.zeros((1, 8, 3)), Mesh(v, [np.array([0, 1, 2, 3]), np.array([4, 5, 6, 7])]))
    turn = head_rotations(["headYaw"], np.array([[-40.0]]))
    r = RigRenderer(rig, size=(64, 64), background=(0, 0, 0)).fit(np.zeros((1, 1)), turn)
    front = r.render_curves(np.zeros(1)).sum(axis=2) > 0
    turned = r.render_curves(np.zeros(1), turn[0]).sum(axis=2) > 0
    assert front.mean() > 0.1 and turned.mean() > 0.1
    assert not np.array_equal(front, turned)
