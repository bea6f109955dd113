"""USD output (issue 25): read back with usd-core and evaluated by UsdSkel's own blend-shape and skinning
queries, it equals keyshape's retargeted vertices (sculpted targets and the ICT-FaceKit rig); frame range,
rate and units; USD's validators report nothing; bad input."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from keyshape.base.errors import InputError
from keyshape.base.formats.obj import write_obj
from keyshape.base.formats.weights import write_weights
from keyshape.cli import main

pxr = pytest.importorskip("pxr", reason="usd-core not installed (pip install 'keyshape[usd]')")

from keyshape.base.formats.usd import read_usd  # noqa: E402


def _mesh():
    """A small curved sheet of quads with UVs (7 x 5 vertices)."""
    from keyshape.base.formats.obj import Mesh
    xs, ys = np.meshgrid(np.linspace(-3, 3, 7), np.linspace(-2, 2, 5))
    v = np.stack([xs.ravel(), ys.ravel(), 0.3 * np.cos(xs.ravel())], axis=1)
    polys = [np.array([r * 7 + c, r * 7 + c + 1, (r + 1) * 7 + c + 1, (r + 1) * 7 + c])
             for r in range(4) for c in range(6)]
    uv = np.stack([(xs.ravel() + 3) / 6, (ys.ravel() + 2) / 4], axis=1)
    return Mesh(v, polys, uv, [p.copy() for p in polys],
                groups={"mouth": np.arange(0, 14), "eyes": np.arange(21, 35)})


def head_size(v: np.ndarray) -> float:
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))


def validation_errors(path) -> list[str]:
    """Errors of USD's own checker: ``UsdUtils.ComplianceChecker`` where usd-core still has it, else its
    successor, every validator of ``pxr.UsdValidation`` (usd-core 24.11 on; ``usdchecker``'s rules)."""
    from pxr import Usd
    try:
        from pxr.UsdUtils import ComplianceChecker
    except ImportError:
        ComplianceChecker = None
    if ComplianceChecker is not None:
        c = ComplianceChecker()
        c.CheckCompliance(str(path))
        return list(c.GetErrors()) + list(c.GetFailedChecks())
    from pxr import UsdValidation as V
    validators = V.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) > 10
    errs = V.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errs if e.GetType() == V.ValidationErrorType.Error]


@pytest.fixture
def scene(tmp_path):
    m = _mesh()
    d = tmp_path / "targets"
    d.mkdir()
    write_obj(d / "neutral.obj", m)
    rng = np.random.default_rng(3)
    cols = ("mouth_0", "mouth_1", "eyes_0", "eyes_1")
    shapes = {c: m.vertices + rng.normal(scale=0.15, size=m.vertices.shape) for c in cols}
    for c, s in shapes.items():
        write_obj(d / f"{c}.obj", m, s)
    w = rng.uniform(0, 1.15, size=(12, len(cols)))
    frames = np.arange(40, 52)
    write_weights(tmp_path / "w.csv", frames, list(cols), w)
    return tmp_path, d, m, cols, w, frames


def _head(n):
    from keyshape.retarget.headpose import head_motion
    th = np.linspace(0, 0.25, n)
    pose = np.stack([(1 + 0.02 * i) * np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0]])
                     + np.array([[0, 0, 3 + 0.5 * i], [0, 0, 2 - 0.2 * i]]) for i, a in enumerate(th)])
    return head_motion(pose)


@pytest.mark.parametrize("form,regions,suffix", [("delta", False, ".usda"), ("delta", True, ".usdc"),
                                                 ("absolute", True, ".usd")])
def test_sculpted_targets_evaluated_by_usdskel_equal_keyshape(scene, form, regions, suffix):
    tmp, d, m, cols, w, frames = scene
    from keyshape.retarget.output.export import export
    from keyshape.retarget.targets.retargeter import Retargeter
    from keyshape.base.geometry import vertex_normals
    from keyshape.retarget.targets.target_set import load_targets
    ts = load_targets(list(cols), d)
    reg = {"mouth": np.arange(0, 18), "eyes": np.arange(17, 35)} if regions else None
    rt = Retargeter(form=form).fit(ts, reg)
    hm = _head(len(w))
    out = tmp / f"take{suffix}"
    info = export(out, rt, frames, w, fps=24.0, head=hm)
    assert info["kind"] == "usd"
    tk = read_usd(out, times=[40, 43, 47, 51])
    truth = rt.transform(w)[[0, 3, 7, 11]]
    tol = 1e-4 * head_size(m.vertices)
    np.testing.assert_allclose(tk.shaped, truth, atol=tol)
    # the head joint: UsdSkel's skinning of the shaped mesh; its scale is a half3 in UsdSkel
    hq = type(hm)(hm.translation, hm.rotation, hm.scale.astype(np.float16).astype(np.float64), hm.angle)
    np.testing.assert_allclose(tk.skinned, hq.apply(rt.transform(w))[[0, 3, 7, 11]], atol=tol)
    np.testing.assert_allclose(tk.skinned, hm.apply(rt.transform(w))[[0, 3, 7, 11]], atol=1e-3 * head_size(m.vertices))
    # normals: the neutral's plus the blend shapes' normal offsets, as the .glb's
    n0 = vertex_normals(ts.neutral, m.triangles)
    base, deltas, names, mw, _ = rt.morph_targets(w)
    nd = np.stack([vertex_normals(base + dd, m.triangles) - n0 for dd in deltas])
    np.testing.assert_allclose(tk.normals, n0 + np.einsum("fk,kvd->fvd", mw[[0, 3, 7, 11]], nd), atol=1e-5)
    assert tk.names == [n for n in names]
    if form == "absolute":
        assert any(n.startswith("keyshape_sum") for n in tk.names)
    assert (tk.fps, tk.frames_per_second, tk.start, tk.end) == (24.0, 24.0, 40.0, 51.0)
    assert tk.meters_per_unit == pytest.approx(0.01) and tk.up_axis == "Y"
    assert validation_errors(out) == []


def test_retarget_command_writes_usd_with_uvs_and_units(scene, capsys):
    tmp, d, m, cols, w, frames = scene
    out = tmp / "cmd.usda"
    write_weights(tmp / "w25.csv", frames, cols, w, fps=25)             # the take's rate travels with the weights
    assert main(["retarget", str(tmp / "w25.csv"), "--targets", str(d), "-o", str(out)]) == 0
    assert "(usd)" in capsys.readouterr().out
    assert read_usd(out).meters_per_unit == pytest.approx(0.01)         # the command: centimetres (ICT-FaceKit)
    from keyshape import api
    api.retarget(api.Weights.load(tmp / "w25.csv"), d).export(out, meters_per_unit=0.001)
    tk = read_usd(out)
    assert len(tk.times) == 12 and tk.fps == 25.0 and tk.meters_per_unit == pytest.approx(0.001)
    np.testing.assert_allclose(tk.weights, w, atol=1e-6)
    np.testing.assert_allclose(tk.skinned, tk.shaped, atol=1e-6)          # no --tracks: the head stays at rest
    from pxr import Usd, UsdGeom
    stage = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Character/Face"))
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [4] * 24               # the OBJ's quads, not triangles
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == "faceVarying"
    np.testing.assert_allclose(np.array(st.ComputeFlattened()), m.uvs[np.concatenate(m.polygon_uvs)], atol=1e-6)


def _toy_rig():
    import importlib.util
    from pathlib import Path
    spec = importlib.util.spec_from_file_location("trp", Path(__file__).parent / "test_rig_poses.py")
    trp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(trp)
    return trp


def test_rig_usd_holds_the_moving_shapes_under_the_rig_names(tmp_path):
    from keyshape.base.formats.obj import Mesh
    from keyshape.retarget.rig.model import Rig
    from keyshape.retarget.output.rig_export import export_rig
    trp = _toy_rig()
    verts, deltas = trp.toy_rig_arrays()
    polys = [np.array([i, i + 1, 48]) for i in range(0, 47)]
    rig = Rig(list(trp.SHAPES), verts, deltas, Mesh(verts, polys))
    curves = np.random.default_rng(1).uniform(0, 1, (9, rig.n_shapes))
    curves[:, 1] = 0.0                                                # a shape that never moves: left out
    export_rig(tmp_path / "rig.usdc", rig, np.arange(100, 109), curves, fps=30.0)
    tk = read_usd(tmp_path / "rig.usdc")
    assert tk.names == [n for j, n in enumerate(rig.names) if j != 1]
    np.testing.assert_allclose(tk.shaped, rig.evaluate(curves), atol=1e-4 * head_size(verts))
    assert (tk.start, tk.end, tk.fps) == (100.0, 108.0, 30.0)
    assert validation_errors(tmp_path / "rig.usdc") == []


@pytest.mark.shared_data
def test_ict_facekit_rig_usd_evaluated_by_usdskel_equals_the_rig(shared_data, tmp_path):
    from keyshape.retarget.rig.model import load_rig
    from keyshape.retarget.output.rig_export import export_rig
    rig = load_rig(shared_data / "ict-facekit")
    rng = np.random.default_rng(7)
    n = 30
    curves = np.zeros((n, rig.n_shapes))
    moving = rng.choice(rig.n_shapes, 20, replace=False)
    curves[:, moving] = rng.uniform(0, 1, (n, 20))
    hm = _head(n)
    frames = np.arange(10, 10 + n)
    export_rig(tmp_path / "ict.usdc", rig, frames, curves, fps=29.97, head=hm, meters_per_unit=0.01)
    pick = [0, 11, 29]
    tk = read_usd(tmp_path / "ict.usdc", times=frames[pick])
    assert tk.names == [rig.names[j] for j in sorted(moving)]
    tol = 1e-4 * head_size(rig.neutral)
    truth = rig.evaluate(curves[pick])
    np.testing.assert_allclose(tk.shaped, truth, atol=tol)
    hq = type(hm)(hm.translation[pick], hm.rotation[pick], hm.scale[pick].astype(np.float16).astype(float),
                  hm.angle[pick])
    np.testing.assert_allclose(tk.skinned, hq.apply(truth), atol=tol)
    assert (tk.start, tk.end, tk.meters_per_unit) == (10.0, 39.0, pytest.approx(0.01))
    assert tk.fps == pytest.approx(29.97)
    assert validation_errors(tmp_path / "ict.usdc") == []


def test_validators_catch_a_broken_stage(tmp_path):
    """The checker used above does report errors: a mesh with skinning attributes but no SkelBindingAPI."""
    from pxr import Usd, UsdGeom
    st = Usd.Stage.CreateNew(str(tmp_path / "bad.usda"))
    m = UsdGeom.Mesh.Define(st, "/M")
    st.SetDefaultPrim(m.GetPrim())
    m.GetPrim().CreateRelationship("skel:skeleton").SetTargets(["/Nowhere"])
    st.GetRootLayer().Save()
    assert validation_errors(tmp_path / "bad.usda")


def test_usd_of_2d_targets_and_without_usd_core_are_one_line_errors(scene, tmp_path, capsys, monkeypatch):
    tmp, d, m, cols, w, frames = scene
    pts = tmp / "pts"
    pts.mkdir()
    for c in cols:
        (pts / f"{c}.pts").write_text("version: 1\nn_points: 3\n{\n0 0\n1 0\n0 1\n}\n")
    assert main(["retarget", str(tmp / "w.csv"), "--targets", str(pts), "-o", str(tmp / "d.usda")]) == 2
    assert not (tmp / "d.usda").exists()
    monkeypatch.setitem(sys.modules, "pxr", None)
    assert main(["retarget", str(tmp / "w.csv"), "--targets", str(d), "-o", str(tmp / "x.usda")]) == 2
    err = capsys.readouterr().err
    assert "keyshape[usd]" in err and not (tmp / "x.usda").exists()
    with pytest.raises(InputError, match="usd-core"):
        from keyshape.base.formats.usd import write_usd
        write_usd(tmp / "y.usda", m.vertices, m.polygons, np.zeros((0, len(m.vertices), 3)), [], np.zeros((2, 0)))


def test_batch_manifest_accepts_usd_output():
    from keyshape.manifest import OUTPUT_FILES, OUTPUTS
    assert "usd" in OUTPUTS and OUTPUT_FILES["usd"].endswith(".usdc")


def test_a_usd_write_that_fails_for_want_of_room_is_one_line(tmp_path):
    """issue 37: USD output onto a full disk (here: a file-size limit, EFBIG) is one line naming the
    user's file, without USD's own error lines, and leaves no temporary."""
    import subprocess
    script = f"""
import resource, signal, sys
import numpy as np
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
from keyshape.base.files import describe_os_error
from keyshape.base.formats.usd import write_usd
rng = np.random.default_rng(0)
v = rng.normal(size=(3000, 3))
polys = [np.array([i, i + 1, i + 2]) for i in range(0, 2997)]
try:
    write_usd({str(tmp_path / 'out.usdc')!r}, v, polys, rng.normal(size=(4, 3000, 3)), list('abcd'),
              rng.uniform(size=(50, 4)))
except OSError as exc:
    print(describe_os_error(exc))
    sys.exit(2)
"""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, (r.stdout, r.stderr)
    line = r.stdout.strip()
    assert "\n" not in line and "out.usdc" in line and ".partial" not in line, line
    assert len(r.stderr.splitlines()) <= 1, r.stderr[:500]
    assert [p.name for p in tmp_path.iterdir()] == []
