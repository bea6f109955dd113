"""The rig .glb and the curves CSV in Blender itself (issue 14): Blender 3.4's glTF importer gets the
rig's shape names and the animation's frame range, and the shipped script
``retarget/data/blender_import_curves.py`` keys the shape keys from the curves CSV and sets the
scene's range and frame rate; keyshape's .usda/.usdc given to Blender's USD importer (Debian's 3.4.1 has
none: built without USD). Needs Debian's ``blender`` (CI installs it); skips where absent."""
from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

BLENDER = shutil.which("blender")
pytestmark = pytest.mark.skipif(BLENDER is None, reason="blender not installed (apt-get install blender)")
SCRIPT = Path(__file__).resolve().parents[1] / "retarget" / "data" / "blender_import_curves.py"

# printed by Blender after the import: the first mesh's shape keys, the action's keyed frames, the scene
REPORT = """
import bpy, json
out = {"scene": [bpy.context.scene.frame_start, bpy.context.scene.frame_end, bpy.context.scene.render.fps]}
for ob in bpy.data.objects:
    keys = ob.data.shape_keys if ob.type == "MESH" else None
    if keys is None:
        continue
    out["keys"] = [k.name for k in keys.key_blocks]
    act = keys.animation_data.action if keys.animation_data else None
    if act is not None:
        out["range"] = list(act.frame_range)
        fc = act.fcurves[0]
        out["first_curve"] = [fc.data_path, [list(k.co) for k in fc.keyframe_points]]
    break
print("KEYSHAPE-REPORT " + json.dumps(out))
"""


def _toy():
    spec = importlib.util.spec_from_file_location("trp", Path(__file__).parent / "test_rig_poses.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _env(tmp_path: Path) -> dict:
    """Blender 3.4's glTF importer imports numpy (and uses ``np.bool``, which numpy 1.24-1.26 lack):
    give it this interpreter's numpy through a folder holding only that package."""
    import os

    import numpy

    lib = tmp_path / "blender_site"
    if not lib.is_dir():
        lib.mkdir()
        src = Path(numpy.__file__).parent
        for p in [src, src.parent / "numpy.libs"]:
            if p.exists():
                (lib / p.name).symlink_to(p)
    return {**os.environ, "PYTHONPATH": str(lib)}


def _run(cmd: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=240, env=_env(tmp_path))


def _blender(args: list[str], tmp_path: Path) -> dict:
    expr = tmp_path / "report.py"
    expr.write_text(REPORT)
    r = _run([BLENDER, "-b", "--factory-startup", *args, "--python", str(expr)], tmp_path)
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("KEYSHAPE-REPORT ")]
    assert r.returncode == 0 and line, r.stdout[-2000:] + r.stderr[-2000:]
    return json.loads(line[-1][len("KEYSHAPE-REPORT "):])


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """A toy rig's .glb and curves CSV of frames 100-111 at 24 fps."""
    from keyshape.base.formats.obj import Mesh
    from keyshape.retarget.rig.model import Rig
    from keyshape.retarget.output.rig_export import export_rig

    trp = _toy()
    tmp = tmp_path_factory.mktemp("blender")
    verts, deltas = trp.toy_rig_arrays()
    polys = [np.array([i, i + 1, 48]) for i in range(0, 47)]
    rig = Rig(list(trp.SHAPES), verts, deltas, Mesh(verts, polys))
    curves = np.random.default_rng(0).uniform(0, 1, (12, len(trp.SHAPES)))
    frames = np.arange(100, 112)
    export_rig(tmp / "take.glb", rig, frames, curves, fps=24.0)
    export_rig(tmp / "curves.csv", rig, frames, curves, fps=24.0)
    return tmp, list(trp.SHAPES), frames, curves


def test_blender_imports_the_rig_glb_with_its_shape_names_and_frame_range(take):
    tmp, names, frames, curves = take
    rep = _blender(["--python-expr", f"import bpy; bpy.ops.import_scene.gltf(filepath={str(tmp / 'take.glb')!r})"],
                   tmp)
    assert rep["keys"] == ["Basis", *names]
    # sampler times are frame / fps, so at the importer's 24 fps the keys sit on the take's frames
    assert rep["range"] == pytest.approx([frames[0], frames[-1]], abs=1e-3)
    path, pts = rep["first_curve"]
    assert path == f'key_blocks["{names[0]}"].value'
    assert [p[0] for p in pts] == pytest.approx(frames, abs=1e-3)
    assert [p[1] for p in pts] == pytest.approx(curves[:, 0], abs=1e-5)


def test_shipped_script_keys_the_curves_and_sets_the_scene_range(take):
    tmp, names, frames, curves = take
    blend = tmp / "out.blend"
    r = _run([BLENDER, "-b", "--factory-startup", "--python", str(SCRIPT), "--",
              str(tmp / "curves.csv"), "--glb", str(tmp / "take.glb"), "--save", str(blend)], tmp)
    assert r.returncode == 0 and blend.is_file(), r.stdout[-2000:] + r.stderr[-2000:]
    rep = _blender([str(blend)], tmp)
    assert rep["scene"] == [int(frames[0]), int(frames[-1]), 24]
    assert rep["keys"] == ["Basis", *names]
    path, pts = rep["first_curve"]
    assert [p[0] for p in pts] == pytest.approx(frames, abs=1e-3)
    assert [p[1] for p in pts] == pytest.approx(np.round(curves[:, 0], 6), abs=1e-5)


# Blender's USD importer, where its build has one: what it makes of each file (objects, the mesh's vertices and
# shape keys, the armature's bones, actions, the scene's range); else that the build has none
USD_REPORT = """
import bpy, json, sys
files = sys.argv[sys.argv.index("--") + 1:]
out = {"version": list(bpy.app.version), "usd": bool(bpy.app.build_options.usd),
       "operator": hasattr(bpy.types, "WM_OT_usd_import"), "files": {}}
for f in files if out["operator"] else []:
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    res = sorted(bpy.ops.wm.usd_import(filepath=f))
    sc = bpy.context.scene
    rep = {"result": res, "scene": [sc.frame_start, sc.frame_end], "objects": {}}
    for ob in bpy.data.objects:
        o = {"type": ob.type, "constraints": [c.type for c in ob.constraints],
             "modifiers": [m.type for m in ob.modifiers]}
        if ob.type == "MESH":
            o["n_vertices"] = len(ob.data.vertices)
            o["shape_keys"] = [k.name for k in ob.data.shape_keys.key_blocks] if ob.data.shape_keys else []
        if ob.type == "ARMATURE":
            o["bones"] = [b.name for b in ob.data.bones]
        rep["objects"][ob.name] = o
    out["files"][f] = rep
print("KEYSHAPE-REPORT " + json.dumps(out))
"""


def test_blender_usd_import_of_keyshape_usda_and_usdc(take):
    """keyshape's .usda (sculpted targets) and .usdc (a rig take with the head) given to Blender's USD importer.
    Debian's Blender 3.4.1 (what CI installs) is built without USD: no ``wm.usd_import`` at all, so a Blender
    user takes the .glb (above). A Blender built with USD (blender.org's) imports the mesh and the frame range
    (its manual's import options); what it makes of the blend shapes and the head joint is reported, not
    asserted (not seen here)."""
    pytest.importorskip("pxr", reason="usd-core not installed (pip install 'keyshape[usd]')")
    from keyshape.base.formats.obj import Mesh
    from keyshape.retarget.headpose import head_motion
    from keyshape.retarget.rig.model import Rig
    from keyshape.retarget.output.rig_export import export_rig
    tmp, names, frames, curves = take
    trp = _toy()
    verts, deltas = trp.toy_rig_arrays()
    rig = Rig(list(trp.SHAPES), verts, deltas, Mesh(verts, [np.array([i, i + 1, 48]) for i in range(0, 47)]))
    th = np.linspace(0, 0.2, len(frames))
    head = head_motion(np.stack([[[np.cos(a), -np.sin(a), 0.1 * i], [np.sin(a), np.cos(a), 0]]
                                 for i, a in enumerate(th)]))
    export_rig(tmp / "take.usdc", rig, frames, curves, fps=24.0, head=head)
    export_rig(tmp / "take.usda", rig, frames, curves, fps=24.0)
    expr = tmp / "usd_report.py"
    expr.write_text(USD_REPORT)
    r = _run([BLENDER, "-b", "--factory-startup", "--python", str(expr), "--", str(tmp / "take.usda"),
              str(tmp / "take.usdc")], tmp)
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("KEYSHAPE-REPORT ")]
    assert r.returncode == 0 and line, r.stdout[-2000:] + r.stderr[-2000:]
    rep = json.loads(line[-1][len("KEYSHAPE-REPORT "):])
    print(json.dumps(rep, indent=1))
    if rep["version"][:2] == [3, 4]:
        # Debian's 3.4.1: built without USD (and without Alembic); the operator does not exist
        assert rep["usd"] is False and rep["operator"] is False and rep["files"] == {}
        return
    if not rep["usd"]:
        assert not rep["operator"]
        return
    for f, got in rep["files"].items():
        assert got["result"] == ["FINISHED"], f
        meshes = [o for o in got["objects"].values() if o["type"] == "MESH"]
        assert [m["n_vertices"] for m in meshes] == [rig.n_vertices], f
        assert got["scene"] == [int(frames[0]), int(frames[-1])], f
