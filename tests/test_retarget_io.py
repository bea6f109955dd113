"""Target loading, outputs (.glb/.csv/OBJ/PNG/video), the retarget command and bad input."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from keyshape import api
from keyshape.cli import main
from keyshape.base.errors import InputError, MissingFileError
from keyshape.base.formats.obj import Mesh, read_obj_vertices, write_obj
from keyshape.retarget.targets.target_set import load_targets, name_key, read_regions
from keyshape.base.formats.weights import read_weights, write_weights

REPO = Path(__file__).resolve().parents[1]


def tiny_mesh():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    uv = np.array([[0, 0], [.5, 0], [.5, 1], [0, 1], [.6, 0], [1, 0], [1, 1], [.6, 1]])   # a seam at x=1
    return Mesh(v, [np.array([0, 1, 2, 3]), np.array([1, 4, 5, 2])], uv,
                [np.array([0, 1, 2, 3]), np.array([4, 5, 6, 7])],
                groups={"mouth": np.array([0]), "eyes": np.array([1])})


@pytest.fixture
def scene(tmp_path):
    """Neutral + 3 OBJ targets named like the weight columns, a weights CSV and tracks."""
    m = tiny_mesh()
    d = tmp_path / "targets"
    d.mkdir()
    write_obj(d / "neutral.obj", m)
    rng = np.random.default_rng(0)
    shapes = {c: m.vertices + rng.normal(scale=0.2, size=m.vertices.shape)
              for c in ("mouth_0", "mouth_1", "eyes_0")}
    for c, s in shapes.items():
        write_obj(d / f"{c.upper()}.obj", m, s)       # names differ in case: matched anyway
    w = rng.uniform(0, 1.1, size=(10, 3))
    write_weights(tmp_path / "w.csv", np.arange(10), list(shapes), w)
    return tmp_path, d, m, shapes, w


def glb_arrays(path):
    """Read back the accessors of a .glb written here: dict of useful arrays."""
    import pygltflib
    g = pygltflib.GLTF2.load_binary(str(path))
    blob = g.binary_blob()

    def acc(i):
        a = g.accessors[i]
        bv = g.bufferViews[a.bufferView]
        n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a.type]
        dt = np.float32 if a.componentType == 5126 else np.uint32
        return np.frombuffer(blob, dt, a.count * n, bv.byteOffset + (a.byteOffset or 0)).reshape(a.count, n)
    prim = g.meshes[0].primitives[0]
    out = {"gltf": g, "base": acc(prim.attributes.POSITION),
           "deltas": np.stack([acc(t["POSITION"]) for t in prim.targets]),
           "names": g.meshes[0].extras["targetNames"], "uv": acc(prim.attributes.TEXCOORD_0)}
    an = g.animations[0]
    for ch in an.channels:
        s = an.samplers[ch.sampler]
        out["times"] = acc(s.input)[:, 0]
        out[ch.target.path] = acc(s.output)
    return out


def test_name_matching():
    assert name_key("mouthSmile_L") == name_key("MouthSmileLeft") == name_key("mouthsmileleft")
    assert name_key("eyeBlink_R") == name_key("eyeBlinkRight")
    assert name_key("mouth_0") == "mouth_0" and name_key("jawOpen") == "jawopen"


def test_glb_roundtrip_with_head_motion(scene):
    tmp, d, m, shapes, w = scene
    from keyshape.retarget.output.export import export
    from keyshape.retarget.headpose import head_motion
    from keyshape.retarget.targets.retargeter import Retargeter
    ts = load_targets(list(shapes), d)
    assert ts.neutral is not None                      # neutral.obj picked up from the folder
    rt = Retargeter(form="delta").fit(ts)
    th = np.linspace(0, 0.3, 10)
    pose = np.stack([np.array([[np.cos(a), -np.sin(a), 5 + i], [np.sin(a), np.cos(a), 2]]) for i, a in enumerate(th)])
    hm = head_motion(pose)
    export(tmp / "o.glb", rt, np.arange(10), w, fps=25, head=hm)
    g = glb_arrays(tmp / "o.glb")
    assert g["names"] == ["MOUTH_0", "MOUTH_1", "EYES_0"]
    from keyshape.base.formats.gltf import split_at_uv_seams
    ids, uv, tri = split_at_uv_seams(ts.mesh)
    assert len(ids) == 8 and sorted(ids) == [0, 1, 1, 2, 2, 3, 4, 5]      # seam vertices 1, 2 split
    np.testing.assert_allclose(g["uv"], uv)
    np.testing.assert_allclose(uv[ids == 0], [[0, 1]])                     # v flipped (glTF origin top-left)
    frames = g["base"] + np.einsum("fk,kvd->fvd", g["weights"].reshape(10, 3), g["deltas"])
    np.testing.assert_allclose(frames, rt.transform(w)[:, ids], atol=1e-5)
    np.testing.assert_allclose(g["times"], np.arange(10) / 25, atol=1e-7)
    np.testing.assert_allclose(g["rotation"], hm.rotation, atol=1e-7)
    np.testing.assert_allclose(g["translation"], hm.translation, atol=1e-5)
    assert g["weights"].max() > 1                      # NNLS weights above 1 kept


def test_absolute_form_glb_adds_sum_target(scene):
    tmp, d, m, shapes, w = scene
    # the paper's literal form: an option of the API, not of the command
    api.retarget(api.Weights.load(tmp / "w.csv"), d, options=api.RetargetOptions(form="absolute")).export(tmp / "a.glb")
    g = glb_arrays(tmp / "a.glb")
    assert g["names"][-1] == "keyshape_sum"
    ts = load_targets(list(shapes), d)
    from keyshape.base.formats.gltf import split_at_uv_seams
    ts.shapes = ts.shapes[:, split_at_uv_seams(ts.mesh)[0]]
    ref = np.einsum("fk,kvd->fvd", w, ts.shapes)            # the paper's sum w_i B_i
    frames = g["base"] + np.einsum("fk,kvd->fvd", g["weights"].reshape(10, 4), g["deltas"])
    np.testing.assert_allclose(frames, ref, atol=1e-5)


def _validator():
    node = shutil.which("node")
    mod = Path(os.environ.get("KEYSHAPE_GLTF_VALIDATOR", REPO / ".cache_node" / "node_modules" / "gltf-validator"))
    if node is None or not (mod / "package.json").is_file():
        pytest.skip("Khronos gltf-validator not installed (npm install gltf-validator into .cache_node, "
                    "or set KEYSHAPE_GLTF_VALIDATOR to its folder)")
    return node, mod


VALIDATE_JS = """
const fs = require('fs'); const v = require(process.argv[2]);
v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[3])), {maxIssues: 100}).then(r => {
  console.log(JSON.stringify({errors: r.issues.numErrors, warnings: r.issues.numWarnings,
                              messages: r.issues.messages.slice(0, 5)}));
}).catch(e => { console.error(String(e)); process.exit(3); });
"""


def run_validator(path, tmp):
    node, mod = _validator()
    js = tmp / "validate.js"
    js.write_text(VALIDATE_JS)
    r = subprocess.run([node, str(js), str(mod), str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.mark.parametrize("form", ["absolute", "delta"])
def test_glb_passes_khronos_validator(scene, form):
    tmp, d, m, shapes, w = scene
    tracks = tmp / "tracks.csv"
    from keyshape.base.formats.tracks import Tracks, write_tracks
    n = 10
    pose = np.tile(np.array([[1.0, 0, 0], [0, 1, 0]]), (n, 1, 1))
    pose[:, 0, 2] = np.arange(n)
    tri = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])                 # 3 points, not collapsed
    write_tracks(tracks, Tracks(np.arange(n), np.arange(n) / 25, np.ones(n), np.ones(n, bool),
                                np.tile(tri, (n, 1, 1)), pose))
    out = tmp / f"{form}.glb"
    from keyshape.base.formats.tracks import read_tracks
    api.retarget(api.Weights.load(tmp / "w.csv"), d, options=api.RetargetOptions(form=form),
                 tracks=read_tracks(tracks)).export(out)
    r = run_validator(out, tmp)
    assert r["errors"] == 0 and r["warnings"] == 0, r["messages"]


def test_validator_catches_a_broken_glb(tmp_path):
    _validator()
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"glTF\x02\x00\x00\x00\x0c\x00\x00\x00")
    assert run_validator(bad, tmp_path)["errors"] > 0


def test_csv_outputs(scene):
    tmp, d, m, shapes, w = scene
    api.retarget(api.Weights.load(tmp / "w.csv"), d).export(tmp / "c.csv", clamp=True)
    fr, names, ww, _ = read_weights(tmp / "c.csv")
    assert names == ["MOUTH_0", "MOUTH_1", "EYES_0"]
    np.testing.assert_allclose(ww, np.clip(w, 0, 1), atol=1e-5)
    arkit = {"MOUTH_0": "jawOpen", "MOUTH_1": "mouthSmile_L", "EYES_0": "eyeBlink_R"}
    for old, new in arkit.items():                      # ARKit-named targets for the Live Link layout
        (d / f"{old}.obj").rename(d / f"{new}.obj")
    fr, names, w, _ = read_weights(tmp / "w.csv")
    write_weights(tmp / "arkit.csv", fr, ["jawOpen", "mouthSmileLeft", "eyeBlinkRight"], w, fps=60)
    assert main(["retarget", str(tmp / "arkit.csv"), "--targets", str(d), "--livelink", "-o", str(tmp / "ll.csv")]) == 0
    rows = (tmp / "ll.csv").read_text().splitlines()
    header, second = rows[0].split(","), dict(zip(rows[0].split(","), rows[2].split(",")))
    assert len(header) == 63 and len(rows) == 11 and second["Timecode"] == "00:00:00:01.000"
    assert float(second["MouthSmileLeft"]) == pytest.approx(w[1, 1], abs=1e-5)


def test_livelink_csv(tmp_path):
    from keyshape.retarget.output.export import csv_rows, livelink_values
    names = ["jawOpen", "mouthSmile_L", "browInnerUp_L", "browInnerUp_R", "mouth_3"]
    w = np.array([[0.5, 0.25, 0.2, 0.4, 0.9]] * 3)
    header, rows = csv_rows(livelink_values(names, w), 30)
    assert header[:3] == ["Timecode", "BlendShapeCount", "EyeBlinkLeft"] and len(header) == 2 + 52 + 9
    assert header[-9:-6] == ["HeadYaw", "HeadPitch", "HeadRoll"] and header[54] == "HeadYaw"
    r = dict(zip(header, rows[1]))
    assert r["BlendShapeCount"] == "61" and r["Timecode"] == "00:00:00:01.000"
    assert float(r["JawOpen"]) == 0.5 and float(r["MouthSmileLeft"]) == 0.25
    assert float(r["BrowInnerUp"]) == pytest.approx(0.3) and float(r["TongueOut"]) == 0
    with pytest.raises(InputError, match="ARKit"):
        livelink_values(["mouth_0"], w[:, :1])


def test_obj_frames_folder(scene):
    tmp, d, m, shapes, w = scene
    out = tmp / "frames"
    api.retarget(api.Weights.load(tmp / "w.csv"), d, options=api.RetargetOptions(form="absolute")).export(out)
    files = sorted(out.glob("frame_*"))
    assert [f.name for f in files[:2]] == ["frame_000000.obj", "frame_000001.obj"] and len(files) == 10
    ts = load_targets(list(shapes), d)
    np.testing.assert_allclose(read_obj_vertices(files[3]), np.einsum("k,kvd->vd", w[3], ts.shapes), atol=1e-5)


def test_2d_png_and_video(tmp_path):
    from keyshape.base.formats.labels import write_pts
    from keyshape.base.schemes import load_scheme
    s = load_scheme("contours48")
    rng = np.random.default_rng(1)
    base = rng.uniform(50, 150, size=(s.n_points, 2))
    for c in ("mouth_0", "mouth_1"):
        write_pts(tmp_path / f"{c}.pts", base + rng.normal(scale=3, size=base.shape))
    write_weights(tmp_path / "w.csv", np.arange(4), ["mouth_0", "mouth_1"], rng.uniform(0, 1, (4, 2)))
    assert main(["retarget", str(tmp_path / "w.csv"), "--targets", str(tmp_path), "-o", str(tmp_path / "png")]) == 0
    assert len(list((tmp_path / "png").glob("frame_*.png"))) == 4
    assert main(["retarget", str(tmp_path / "w.csv"), "--targets", str(tmp_path), "-o", str(tmp_path / "v.mp4")]) == 0
    from keyshape.base.formats.video import video_info
    assert video_info(tmp_path / "v.mp4").n_frames == 4
    assert main(["retarget", str(tmp_path / "w.csv"), "--targets", str(tmp_path), "-o", str(tmp_path / "x.glb")]) == 2
    assert not (tmp_path / "x.glb").exists()


def test_regions_from_json_and_obj_groups(scene, tmp_path):
    tmp, d, m, shapes, w = scene
    (tmp / "regions.json").write_text(json.dumps({"mouth": [0, 3], "eyes": "eyes"}))
    ts = load_targets(list(shapes), d)
    g = read_regions(tmp / "regions.json", ts.mesh)
    assert list(g["mouth"]) == [0, 3] and list(g["eyes"]) == [1, 2, 4, 5]
    assert main(["retarget", str(tmp / "w.csv"), "--targets", str(d), "--regions", str(tmp / "regions.json"),
                 "-o", str(tmp / "r.glb")]) == 0
    (tmp / "bad_regions.json").write_text(json.dumps({"nose": [0]}))
    with pytest.raises(InputError, match="bad_regions.json.*'mouth'"):
        main_raise(["retarget", str(tmp / "w.csv"), "--targets", str(d), "--regions",
                    str(tmp / "bad_regions.json"), "-o", str(tmp / "r2.glb")])
    assert not (tmp / "r2.glb").exists()


def main_raise(argv):
    """Run the command's function directly so the error propagates (main() prints it)."""
    from keyshape.cli import build_parser
    args = build_parser().parse_args(argv)
    return args.func(args)


# ---------------------------------------------------------------- bad input

def _replace_line(path, index, text):
    lines = path.read_text().splitlines()
    lines[index] = text
    path.write_text("\n".join(lines) + "\n")


BAD_INPUTS = {
    "different vertex counts": (lambda tmp, d: write_obj(d / "EYES_0.obj", Mesh(np.zeros((4, 3)), [])),
                                r"EYES_0\.obj.*4 vertices, expected 6"),
    "broken OBJ line": (lambda tmp, d: _replace_line(d / "MOUTH_1.obj", 2, "v 1.0 oops 2.0"),
                        r"MOUTH_1\.obj, line 3: broken vertex line"),
    "column without target": (lambda tmp, d: (d / "EYES_0.obj").unlink(), r"\['eyes_0'\] have no target.*targets"),
    "NaN weight": (lambda tmp, d: _replace_line(tmp / "w.csv", 4, "3,0.1,nan,0.2"),
                   r"w\.csv, line 5: nan in column 'mouth_1'"),
}


@pytest.mark.parametrize("suffix", [".glb", ".csv", ""])
@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_names_the_file_and_writes_nothing(scene, case, suffix):
    tmp, d, m, shapes, w = scene
    breaker, message = BAD_INPUTS[case]
    breaker(tmp, d)
    argv = ["retarget", str(tmp / "w.csv"), "--targets", str(d), "-o", str(tmp / f"out{suffix}")]
    with pytest.raises(InputError, match=message):
        main_raise(argv)
    assert main(argv) == 2
    assert sorted(p.name for p in tmp.iterdir()) == ["targets", "w.csv"]     # nothing half-written


def test_mapping(scene):
    tmp, d, m, shapes, w = scene
    (tmp / "map.json").write_text(json.dumps({"mouth_0": "targets/EYES_0.obj", "mouth_1": "targets/MOUTH_1.obj",
                                              "eyes_0": "targets/MOUTH_0.obj"}))
    ts = load_targets(list(shapes), d, mapping=tmp / "map.json")
    assert ts.names == ["EYES_0", "MOUTH_1", "MOUTH_0"]
    np.testing.assert_array_equal(ts.neutral, m.vertices)        # the folder's neutral.obj, map or not
    moved = m.vertices + 1.0
    write_obj(tmp / "other_neutral.obj", m, moved)
    (tmp / "map3.json").write_text(json.dumps({"mouth_0": "targets/MOUTH_0.obj", "mouth_1": "targets/MOUTH_1.obj",
                                               "eyes_0": "targets/EYES_0.obj", "neutral": "other_neutral.obj"}))
    ts = load_targets(list(shapes), d, mapping=tmp / "map3.json")
    np.testing.assert_allclose(ts.neutral, moved, atol=1e-6)       # the mapping's "neutral" entry wins
    (tmp / "map2.json").write_text(json.dumps({"mouth_0": "targets/nothere.obj"}))
    with pytest.raises(MissingFileError, match=r"nothere\.obj.*'mouth_0'.*map2\.json"):
        api.retarget(api.Weights.load(tmp / "w.csv"), d, mapping=tmp / "map2.json")
    assert not (tmp / "o.glb").exists()


def test_weights_csv_errors(tmp_path):
    p = tmp_path / "w.csv"
    p.write_text("time,a\n0,1\n")
    with pytest.raises(InputError, match=r"w\.csv, line 1: expected a header"):
        read_weights(p)
    p.write_text("frame,a,b\n0,1\n")
    with pytest.raises(InputError, match=r"line 2: 2 fields, expected 3"):
        read_weights(p)
    p.write_text("frame,a\n0,x\n")
    with pytest.raises(InputError, match=r"line 2: not a number: 'x'"):
        read_weights(p)


def test_mixed_2d_3d_targets(scene):
    tmp, d, m, shapes, w = scene
    from keyshape.base.formats.labels import write_pts
    write_pts(d / "EYES_0.pts", np.zeros((6, 2)))
    (d / "EYES_0.obj").unlink()
    with pytest.raises(InputError, match="mix OBJ meshes and 2D drawings"):
        load_targets(list(shapes), d)


# ---------------------------------------------------------------- render and demo targets

def test_render_covers_triangle_and_zbuffer():
    from keyshape.retarget.output.render import OrthoCamera, render
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 1], [10, 0, 1], [0, 10, 1.0]])
    cam = OrthoCamera(0, 10, 10.0, 100, 100)           # 10 px per unit, y up -> rows down
    img = render(v[:3], np.array([[0, 1, 2]]), cam, colour=(255, 255, 255), background=(0, 0, 0), ambient=1.0)
    covered = (img[..., 0] > 0).sum()
    assert abs(covered - 5000) < 120                    # half of the 100x100 square
    near = render(v, np.array([[0, 1, 2], [3, 4, 5]]), cam, colour=(255, 255, 255), background=(0, 0, 0))
    assert (near[..., 0] > 0).sum() == covered


def test_side_by_side():
    from keyshape.retarget.output.render import side_by_side
    out = side_by_side(np.zeros((288, 360), np.uint8), np.full((320, 320, 3), 200, np.uint8), gap=4)
    assert out.shape == (288, 360 + 4 + 288, 3) and out[0, -1, 0] == 200


def test_demo_targets_builder(tmp_path):
    from keyshape.retarget.targets.demo import demo_targets, load_expressions, write_demo_targets
    ex = load_expressions()
    assert ex.deltas.shape[1:] == ex.neutral.shape and "jawOpen" in ex.names
    ts = demo_targets({"mouth_0": {"jawOpen": 0.7, "mouthSmileLeft": 0.3}, "eyes_0": {"eyeBlink_L": 1.0}})
    j, s = ex.names.index("jawOpen"), ex.names.index("mouthSmile_L")
    np.testing.assert_allclose(ts.shapes[0], ex.neutral + 0.7 * ex.deltas[j] + 0.3 * ex.deltas[s], atol=1e-12)
    from keyshape.retarget.targets.demo import demo_regions
    from keyshape.retarget.targets.retargeter import Retargeter
    reg = demo_regions(ex)
    assert len(reg["mouth"]) == 20 and len(reg["eyes"]) == 22
    rt = Retargeter(band=2.0).fit(ts, reg)           # delta form (neutral), geodesic band on the face
    out = rt.transform(np.array([[1.0, 0.0]]))[0]    # mouth key only: the eye stays open
    eye_only = (np.abs(ts.shapes[1] - ts.neutral).max(axis=1) > 0.05) \
        & (rt.region_weights_[rt.region_names_.index("eyes")] == 1)
    assert eye_only.sum() > 50
    np.testing.assert_allclose(out[eye_only], ts.neutral[eye_only])
    jaw = np.abs(ts.shapes[0] - ts.neutral).max(axis=1).argmax()
    np.testing.assert_allclose(out[jaw], ts.shapes[0][jaw])      # the jaw opens fully
    ts2 = demo_targets({"mouth_0": {"jawOpen": 1.0}}, neutral_coeffs={"jawOpen": 0.2})
    np.testing.assert_allclose(ts2.neutral, ex.neutral + 0.2 * ex.deltas[j], atol=1e-12)
    np.testing.assert_allclose(ts.neutral, ex.neutral)
    with pytest.raises(InputError, match="unknown expression 'tongueOut'"):
        demo_targets({"mouth_0": {"tongueOut": 1.0}})
    write_demo_targets(tmp_path / "t", {"mouth_0": {"jawOpen": 1.0}})
    assert sorted(p.name for p in (tmp_path / "t").glob("*.obj")) == ["mouth_0.obj", "neutral.obj"]
    assert (REPO / "retarget" / "data" / "LICENSE-ICT-FaceKit.txt").read_text().startswith("MIT License")
    assert (REPO / "retarget" / "data" / "ict_face.npz").stat().st_size < 3e6


@pytest.mark.shared_data
def test_ict_facekit_weights_against_direct_blend(shared_data, tmp_path):
    """Real artist data: ICT-FaceKit expression meshes as targets, checked against
    neutral + sum w_i (E_i - neutral) computed directly from the OBJ files."""
    ict = shared_data / "ict-facekit"
    names = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "eyeBlink_L", "browInnerUp_R"]
    rng = np.random.default_rng(2)
    w = rng.uniform(0, 1, size=(2, len(names)))
    write_weights(tmp_path / "w.csv", np.arange(2), names, w)
    out = tmp_path / "frames"
    assert main(["retarget", str(tmp_path / "w.csv"), "--targets", *[str(ict / f"{n}.obj") for n in names],
                 "--neutral", str(ict / "generic_neutral_mesh.obj"), "-o", str(out)]) == 0
    neutral = read_obj_vertices(ict / "generic_neutral_mesh.obj")
    direct = neutral.copy()
    for j, n in enumerate(names):
        direct += w[1, j] * (read_obj_vertices(ict / f"{n}.obj") - neutral)
    got = read_obj_vertices(out / "frame_000001.obj")
    np.testing.assert_allclose(got, direct, atol=2e-6)     # written with 6 decimals (cm)
    assert np.abs(direct - neutral).max() > 0.5             # the expressions really move (cm)
    # the shipped subset is the same data on the face skin (float16 deltas)
    from keyshape.retarget.targets.demo import load_expressions
    ex = load_expressions()
    np.testing.assert_allclose(ex.neutral, neutral[:len(ex.neutral)], atol=1e-5)
    j = ex.names.index("jawOpen")
    np.testing.assert_allclose(ex.deltas[j], (read_obj_vertices(ict / "jawOpen.obj") - neutral)[:len(ex.neutral)],
                               atol=2e-3)


def test_3d_video_preview(scene):
    tmp, d, m, shapes, w = scene
    assert main(["retarget", str(tmp / "w.csv"), "--targets", str(d), "-o", str(tmp / "v.mp4")]) == 0
    from keyshape.base.formats.video import video_info
    assert video_info(tmp / "v.mp4").n_frames == 10
