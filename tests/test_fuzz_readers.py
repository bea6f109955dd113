"""Property tests of every file reader: any bytes either parse into finite, validated data or raise a
:class:`~keyshape.base.errors.KeyshapeError` (one line, naming the file); never another exception.

Each reader gets byte strings built from a valid file of its format: random bytes, truncations,
flipped bytes, numbers replaced by ``1e300``/``nan``/``inf``/huge integers, deleted spans and
duplicated lines (a few hundred examples each in the default suite, a few thousand in the slow one).
The model file is also fuzzed structurally (arrays replaced by NaN, wrong shapes, missing keys).
"""
from __future__ import annotations

import io
import json
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from keyshape.base.errors import InputError, KeyshapeError

TOKENS = [b"1e300", b"-1e300", b"nan", b"NaN", b"inf", b"-inf", b"Infinity", b"1e999", b"", b"0", b"-1", b"1e-320",
          b"99999999999999999999999", b"\xff\xfe\x00", b",", b"\n", b"{", b"}", b"[", b"]", b'"', b"null", b"true",
          b" ", b"\t", b"1.5", b"-0", b"\x00", b"# keyshape partial tracks:", b"version: 1", b"n_points: 3"]
NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


@st.composite
def mutated(draw, seed: bytes):
    """Bytes near ``seed``: the valid file with a few edits (or, once in ten, random bytes)."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=300))
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.integers(0, 6))
        i = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == 0 and data:
            data[i] = draw(st.integers(0, 255))
        elif op == 1:
            del data[draw(st.integers(0, len(data))):]
        elif op == 2:
            data[i:i] = draw(st.sampled_from(TOKENS))
        elif op in (3, 4):
            spans = [m.span() for m in NUMBER.finditer(bytes(data))]
            if spans:
                a, b = spans[draw(st.integers(0, len(spans) - 1))]
                data[a:b] = draw(st.sampled_from(TOKENS))
        elif op == 5:
            j = draw(st.integers(i, min(len(data), i + 40)))
            del data[i:j]
        else:
            lines = bytes(data).split(b"\n")
            k = draw(st.integers(0, len(lines) - 1))
            lines.insert(draw(st.integers(0, len(lines))), lines[k])
            data = bytearray(b"\n".join(lines))
    return bytes(data)


def _finite(*arrays) -> None:
    for a in arrays:
        a = np.asarray(a)
        if a.dtype.kind == "f":
            assert not np.isinf(a).any(), "reader returned infinity"


# ------------------------------------------------------------------ seeds: one valid file per format
def _seed_pts(d: Path) -> bytes:
    from keyshape.base.formats.labels import write_pts
    write_pts(d / "s.pts", np.random.default_rng(0).uniform(10, 300, (12, 2)))
    return (d / "s.pts").read_bytes()


def _seed_tracks(d: Path) -> bytes:
    from keyshape.base.formats.tracks import Tracks, write_tracks
    rng = np.random.default_rng(1)
    n, p = 5, 4
    pose = np.tile([[1.0, 0, 3], [0, 1.0, 4]], (n, 1, 1))
    write_tracks(d / "s.csv", Tracks(np.arange(n), np.arange(n) / 30, np.ones(n), np.ones(n, bool),
                                     rng.uniform(0, 200, (n, p, 2)), pose))
    return (d / "s.csv").read_bytes()


def _seed_weights(d: Path) -> bytes:
    from keyshape.base.formats.weights import write_weights
    write_weights(d / "w.csv", np.arange(4), ["mouth_0", "mouth_1", "eyes_0"],
                  np.random.default_rng(2).uniform(0, 1, (4, 3)), np.array([0, 1, 0, 0]))
    return (d / "w.csv").read_bytes()


def _seed_keys(d: Path) -> bytes:
    from keyshape.base.formats.keys import RegionKeys, write_keys
    rng = np.random.default_rng(3)
    pts = np.array([0, 1, 2])
    rk = RegionKeys("mouth", "spread", pts, np.array([0, 5]), rng.normal(size=(2, 3, 2)), rng.normal(size=(3, 2)),
                    np.array([True, True]))
    write_keys(d / "k.json", "contours48", 48, [rk])
    return (d / "k.json").read_bytes()


def _seed_regions(d: Path) -> bytes:
    return json.dumps({"mouth": [0, 1, 2, 5], "eyes": [3, 4]}).encode()


def _seed_obj(d: Path) -> bytes:
    return (b"# cube corner\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1.5\nvt 0 0\nvt 1 0\nvt 0 1\n"
            b"g mouth\nf 1/1 2/2 3/3\ng eyes\nf 1 2 4\nf 1 3 4\n")


def _take():
    from keyshape.base.formats.markers import Markers
    rng = np.random.default_rng(4)
    pos = rng.normal(0, 50, (6, 4, 3))
    pos[2, 1] = np.nan
    return Markers(pos, ["a", "b", "c", "d"], 120.0, "mm")


def _seed_trc(d: Path) -> bytes:
    from keyshape.base.formats.markers import write_trc
    write_trc(d / "t.trc", _take())
    return (d / "t.trc").read_bytes()


def _seed_c3d(d: Path) -> bytes:
    from keyshape.base.formats.markers import write_c3d
    write_c3d(d / "t.c3d", _take())
    return (d / "t.c3d").read_bytes()


def _seed_mesh_markers(d: Path) -> bytes:
    return json.dumps({"lip": 3, "chin": [0.5, 1.0, -2.0], "nose": {"position": [0.0, 1.0, 2.0], "vertex": 1}}).encode()


# ------------------------------------------------------------------ readers and what a success must satisfy
def _read_pts(p):
    from keyshape.base.formats.labels import read_pts
    _finite(read_pts(p))


def _read_tracks(p):
    from keyshape.base.formats.tracks import read_tracks
    t = read_tracks(p)
    _finite(t.points, t.pose, t.time, t.confidence)
    assert (np.diff(t.frame) == 1).all()


def _read_weights(p):
    from keyshape.base.formats.weights import read_weights
    fr, names, w, flag = read_weights(p)
    assert np.isfinite(w).all() and (np.diff(fr) == 1).all() and len(names) == w.shape[1]


def _read_keys(p):
    from keyshape.base.formats.keys import read_keys
    _, n, regions = read_keys(p)
    for rk in regions:
        assert np.isfinite(rk.keys).all() and np.isfinite(rk.neutral).all()
        assert ((rk.points >= 0) & (rk.points < n)).all()


def _read_regions(p):
    from keyshape.retarget.targets.target_set import read_regions
    for idx in read_regions(p).values():
        assert np.asarray(idx).dtype.kind in "iu" and (np.asarray(idx) >= 0).all()


def _read_obj(p):
    from keyshape.base.formats.obj import read_obj
    m = read_obj(p)
    assert np.isfinite(m.vertices).all() and np.isfinite(m.uvs).all()
    for poly in m.polygons:
        assert ((poly >= 0) & (poly < m.n_vertices)).all()


def _read_take(p):
    from keyshape.base.formats.markers import read_markers
    m = read_markers(p)
    _finite(m.positions)
    assert np.isfinite(m.rate) and m.rate > 0


def _read_mesh_markers(p):
    from keyshape.base.formats.markers import read_mesh_markers
    for v in read_mesh_markers(p).values():
        assert isinstance(v, int) or np.isfinite(np.asarray(v, float)).all()


READERS = {
    "pts": (_seed_pts, ".pts", _read_pts),
    "tracks": (_seed_tracks, ".csv", _read_tracks),
    "weights": (_seed_weights, ".csv", _read_weights),
    "keys": (_seed_keys, ".json", _read_keys),
    "regions": (_seed_regions, ".json", _read_regions),
    "obj": (_seed_obj, ".obj", _read_obj),
    "trc": (_seed_trc, ".trc", _read_take),
    "c3d": (_seed_c3d, ".c3d", _read_take),
    "marker_json": (_seed_mesh_markers, ".json", _read_mesh_markers),
}


def _fuzz(name: str, n: int, monkeypatch) -> None:
    import keyshape.base.formats.markers as mk

    monkeypatch.setattr(mk, "C3D_SECONDS", 3.0)     # ezc3d loops on some damaged files: give up sooner
    seed_fn, suffix, read = READERS[name]
    with tempfile.TemporaryDirectory(prefix=f"fuzz-{name}-") as tmp:
        _fuzz_in(Path(tmp), seed_fn, suffix, read, n)


def _fuzz_in(d: Path, seed_fn, suffix: str, read, n: int) -> None:
    seed = seed_fn(d)
    read(_write(d, suffix, seed))                   # the seed itself is valid

    @settings(max_examples=n, deadline=None, database=None, derandomize=n < 1000,
              suppress_health_check=list(HealthCheck))
    @given(mutated(seed))
    def run(data):
        p = _write(d, suffix, data)
        try:
            read(p)
        except KeyshapeError as exc:
            assert "\n" not in str(exc).strip(), "error message is more than one line"

    run()


def _write(d: Path, suffix: str, data: bytes) -> Path:
    p = d / f"f{suffix}"
    p.write_bytes(data)
    return p


@pytest.mark.parametrize("name", sorted(READERS))
def test_reader_fuzz(name, monkeypatch):
    _fuzz(name, 60 if name == "c3d" else 250, monkeypatch)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(READERS))
def test_reader_fuzz_long(name, monkeypatch):
    _fuzz(name, 600 if name == "c3d" else 3000, monkeypatch)


# ------------------------------------------------------------------ the model file, structurally
@pytest.fixture(scope="module")
def model_arrays(tmp_path_factory):
    from keyshape.data_synth.video import SyntheticVideo
    from keyshape.tracker.eigenpoints import AppearanceModel

    sv = SyntheticVideo(8, 0, (160, 120), 30.0)
    idx = [0, 2, 4, 6]
    m = AppearanceModel("contours48", n_morphs=4, rng=0).fit([sv.frame(i) for i in idx], sv.points[idx])
    buf = io.BytesIO()
    mf = m.to_file()
    from keyshape.base.formats.model import write_model
    d = tmp_path_factory.mktemp("fuzz-model")
    write_model(d / "m.npz", mf)
    with np.load(d / "m.npz") as z:
        arrays = {k: z[k] for k in z.files}
    del buf
    return d, arrays


@st.composite
def model_edits(draw, keys):
    edits = []
    for _ in range(draw(st.integers(1, 3))):
        k = draw(st.sampled_from(keys))
        op = draw(st.sampled_from(["nan", "inf", "big", "drop", "shape", "empty", "text", "meta"]))
        edits.append((k, op, draw(st.integers(0, 10 ** 6)), draw(st.sampled_from(TOKENS))))
    return edits


def _apply(arrays: dict, edits) -> dict:
    a = dict(arrays)
    for k, op, r, tok in edits:
        if k not in a:
            continue
        v = np.array(a[k])
        if op == "meta" or k == "meta":
            text = str(a["meta"])
            spans = [m.span() for m in re.finditer(r"-?\d+(?:\.\d+)?", text)]
            if spans:
                s, e = spans[r % len(spans)]
                text = text[:s] + tok.decode("latin-1") + text[e:]
            a["meta"] = np.array(text)
        elif op == "drop":
            del a[k]
        elif op == "empty":
            a[k] = v.reshape(-1)[:0]
        elif op == "text":
            a[k] = np.array("x")
        elif op == "shape" and v.size:
            a[k] = v.reshape(-1)[: max(1, v.size - 1 - r % max(v.size, 1))]
        elif v.size and v.dtype.kind == "f":
            v.reshape(-1)[r % v.size] = {"nan": np.nan, "inf": np.inf, "big": 1e300}[op] if op in ("nan", "inf", "big") else 0
            a[k] = v
    return a


def _fuzz_model(model_arrays, n):
    from keyshape.tracker.eigenpoints import AppearanceModel

    d, arrays = model_arrays
    AppearanceModel.load(d / "m.npz")

    @settings(max_examples=n, deadline=None, database=None, derandomize=n < 1000,
              suppress_health_check=list(HealthCheck))
    @given(st.one_of(model_edits(sorted(arrays)), mutated((d / "m.npz").read_bytes()).map(lambda b: b)))
    @example([("components", "meta", 138145, b"null")])     # a null in the header's parameters (the long run's find)
    def run(edit):
        p = d / "f.npz"
        if isinstance(edit, bytes):
            p.write_bytes(edit)
        else:
            with open(p, "wb") as f:
                np.savez(f, **_apply(arrays, edit))
        try:
            m = AppearanceModel.load(p)
        except KeyshapeError as exc:
            assert "\n" not in str(exc).strip()
            return
        assert np.isfinite(m.components_).all() and np.isfinite(m.mean_).all()

    run()


@pytest.mark.parametrize("name, value", [("ridge", None), ("ridge", -1.0), ("ridge", "1"), ("margin", -0.5),
                                         ("face_width", 6.5), ("variance", 0.0), ("regions", 1), ("n_components", 0),
                                         ("lip_grow", True), ("ridge", 1e300), ("bogus", 1)])
def test_model_parameters_out_of_kind_or_range_are_refused(model_arrays, tmp_path, name, value):
    """A model file's constructor parameters are checked when it is read: a null ridge (found by the long fuzz
    test) crashed the load with a TypeError; every such file is a one-line InputError naming the parameter."""
    import json

    from keyshape.tracker.eigenpoints import AppearanceModel

    _, arrays = model_arrays
    meta = json.loads(str(arrays["meta"]))
    meta["params"][name] = value
    p = tmp_path / "m.npz"
    with open(p, "wb") as f:
        np.savez(f, **{**arrays, "meta": np.array(json.dumps(meta))})
    with pytest.raises(InputError, match=f"parameter.*{name}") as exc:
        AppearanceModel.load(p)
    assert "m.npz" in str(exc.value) and "\n" not in str(exc.value).strip()


@pytest.mark.filterwarnings("ignore::hypothesis.errors.HypothesisWarning")
def test_model_fuzz(model_arrays):
    _fuzz_model(model_arrays, 250)


@pytest.mark.slow
def test_model_fuzz_long(model_arrays):
    _fuzz_model(model_arrays, 3000)


# ------------------------------------------------------------------ issue 27: the manifest, POSES.json, the
# ownership record, the rig folder and the page's request bodies; readers fuzzed against their own writers
MANIFEST_SEED = b'''[settings]
outputs = ["tracks", "weights", "glb"]
smooth = "none"
solver = "smooth"
ridge = 0.03
smooth_lambda = 0.1

[actors.anna]
video = "anna/rom.mp4"
labels = "anna/labels"
keys = 8
components = 12
morphs = 120
seed = 3
selector = "greedy"
regions = ["mouth", "eyes"]

[[takes]]
actor = "anna"
video = "anna/take01.mp4"
frames = [0, 600]
name = "take01"
'''


def _seed_manifest(d: Path) -> bytes:
    return MANIFEST_SEED


def _read_manifest(p):
    import math

    from keyshape.manifest import ACTOR_FILES, read_manifest
    m = read_manifest(p)
    assert math.isfinite(m.settings.ridge) and m.settings.ridge >= 0
    assert math.isfinite(m.settings.smooth_lambda) and m.settings.smooth_lambda >= 0
    for a in m.actors.values():
        assert a.keys >= 1 and 0 <= a.seed < 2 ** 32 and (a.components is None or a.components >= 1) and a.morphs >= 0
    for t in m.takes:
        assert t.name not in ACTOR_FILES and "/" not in t.name and t.name not in (".", "..")
        assert t.start >= 0 and (t.stop is None or t.stop > t.start)


def _toy_poses() -> dict:
    return {"keys": {"file": "keys.json", "scheme": "contours48", "model": "sha256:0123456789abcdef"},
            "rig": {"n_vertices": 50, "shapes": ["jawOpen", "mouthSmile_L", "eyeBlink_L"]},
            "range": [0.0, 1.0],
            "regions": {"mouth": {"shapes": ["jawOpen", "mouthSmile_L"], "neutral": {"jawOpen": 0.12},
                                  "keys": {"mouth_0": {"jawOpen": 0.41, "mouthSmile_L": 0.3}, "mouth_1": {}}},
                        "eyes": {"shapes": ["eyeBlink_L"], "neutral": {},
                                 "keys": {"eyes_0": {"eyeBlink_L": 1.0}}}}}


def _seed_poses(d: Path) -> bytes:
    from keyshape.base.formats.poses import write_poses
    write_poses(d / "s.json", _toy_poses())
    return (d / "s.json").read_bytes()


def _read_poses(p):
    from keyshape.base.formats.poses import MAX_RANGE, read_poses
    lib = read_poses(p, ["jawOpen", "mouthSmile_L", "eyeBlink_L"])
    lo, hi = lib["range"]
    assert np.isfinite([lo, hi]).all() and -MAX_RANGE <= lo < hi <= MAX_RANGE
    for reg in lib["regions"].values():
        for pose in [reg.get("neutral", {}), *reg["keys"].values()]:
            for s, v in pose.items():
                assert s in reg["shapes"] and lo - 1e-9 <= v <= hi + 1e-9


def _seed_record(d: Path) -> bytes:
    return json.dumps({"written_by": "keyshape", "version": 2,
                       "outputs": {"retarget": ["frame_000000.obj", "sub/frame_000001.obj"],
                                   "compare": ["errors.csv"], "legacy": ["a.txt"]}}).encode()


def _read_record(p):
    """The ownership record read as the folder outputs do: every entry a plain relative path inside."""
    import os

    from keyshape.base.files import MANIFEST, _read_manifest
    folder = p.parent / "out"
    folder.mkdir(exist_ok=True)
    (folder / MANIFEST).write_bytes(p.read_bytes())
    rec = _read_manifest(folder)
    for kind, files in rec.items():
        assert isinstance(kind, str) and kind
        for f in files:
            assert not os.path.isabs(f) and ".." not in f.split("/") and "\\" not in f and f == os.path.normpath(f)
            assert os.path.realpath(folder / f).startswith(os.path.realpath(folder) + os.sep)


def _seed_rig_shape(d: Path) -> bytes:
    from keyshape.base.formats.obj import Mesh, write_obj
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    write_obj(d / "s.obj", Mesh(v + 0.1, [np.array([0, 1, 2]), np.array([0, 2, 3])]))
    return (d / "s.obj").read_bytes()


def _read_rig(p):
    """A rig folder whose shape ``jawOpen.obj`` is the fuzzed file (the neutral stays valid)."""
    import shutil

    from keyshape.base.formats.obj import Mesh, write_obj
    from keyshape.retarget.rig.model import load_rig
    rig = p.parent / "rig"
    shutil.rmtree(rig, ignore_errors=True)
    rig.mkdir()
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    write_obj(rig / "neutral.obj", Mesh(v, [np.array([0, 1, 2]), np.array([0, 2, 3])]))
    (rig / "jawOpen.obj").write_bytes(p.read_bytes())
    r = load_rig(rig)
    assert np.isfinite(r.deltas).all() and np.isfinite(r.neutral).all() and r.names == ["jawOpen"]


READERS.update({
    "manifest": (_seed_manifest, ".toml", _read_manifest),
    "poses": (_seed_poses, ".json", _read_poses),
    "outputs_record": (_seed_record, ".json", _read_record),
    "rig_folder": (_seed_rig_shape, ".obj", _read_rig),
})


@pytest.mark.parametrize("name", ["manifest", "poses", "outputs_record", "rig_folder"])
def test_reader_fuzz_issue27(name, monkeypatch):
    _fuzz(name, 150, monkeypatch)


# ------------------------------------------------------------------ the pose page's request bodies
def _fuzz_pose_page(n: int) -> None:
    from keyshape.base.formats.poses import read_poses
    from server_helpers import request, serving
    from test_pose_edit import pose_page_server

    with tempfile.TemporaryDirectory(prefix="fuzz-page-") as tmp:
        d = Path(tmp)
        seed = b'{"pose": {"jawOpen": 0.5, "mouthSmile_L": 0.25}}'
        with serving(pose_page_server(d)) as server:
            names = list(read_poses(d / "poses.json")["rig"]["shapes"])

            @settings(max_examples=n, deadline=None, database=None, derandomize=n < 1000,
                      suppress_health_check=list(HealthCheck))
            @given(mutated(seed), st.sampled_from(["mouth_0", "eyes_0", "mouth_9"]))
            def run(body, key):
                status, reply = request(server, "PUT", f"/api/poses/{key}", body)
                assert status == 200 or 400 <= status < 500, (status, reply)   # never a 5xx, always an answer
                if status != 200:
                    assert "error" in json.loads(reply)
                read_poses(d / "poses.json", names)                          # what the page wrote reads back

            run()


def test_pose_page_request_fuzz():
    _fuzz_pose_page(120)


@pytest.mark.slow
def test_pose_page_request_fuzz_long():
    _fuzz_pose_page(1500)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["manifest", "poses", "outputs_record", "rig_folder"])
def test_reader_fuzz_issue27_long(name, monkeypatch):
    _fuzz(name, 2000, monkeypatch)


# ------------------------------------------------------------------ round trips through the API's save
@settings(max_examples=150, deadline=None, database=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.integers(0, 5), st.integers(1, 4), st.integers(0, 1000),
       st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                          st.sampled_from([1e300, -1e7, 0.0, 1.0])), min_size=1, max_size=40),
       st.sampled_from(["contiguous", "gap", "reversed", "repeated", "fractional"]))
def test_weights_save_then_load_round_trips_or_refuses(n, k, first, pool, frames_kind):
    """Whatever the API is given, ``Weights.save`` either writes a file ``Weights.load`` reads back
    (the same numbers to 6 decimals) or refuses with a one-line InputError and writes nothing."""
    from keyshape import api
    from keyshape.base.errors import InputError
    values = np.resize(np.asarray(pool, dtype=float), (n, k))
    frames = np.arange(first, first + n, dtype=float)
    if frames_kind == "gap" and n > 1:
        frames[-1] += 2
    elif frames_kind == "reversed":
        frames = frames[::-1].copy()
    elif frames_kind == "repeated" and n > 1:
        frames[1] = frames[0]
    elif frames_kind == "fractional" and n:
        frames = frames + 0.5
    with tempfile.TemporaryDirectory(prefix="rt-w-") as tmp:
        d = Path(tmp)
        try:
            w = api.Weights(frames, [f"mouth_{j}" for j in range(k)], values)
            w.save(d / "w.csv")
        except InputError as exc:
            assert "\n" not in str(exc)
            assert not (d / "w.csv").exists()
            return
        back = api.Weights.load(d / "w.csv")
        np.testing.assert_array_equal(back.frames, w.frames)
        np.testing.assert_allclose(back.values, w.values, atol=1e-6, rtol=1e-6)


@settings(max_examples=60, deadline=None, database=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.lists(st.sampled_from([0.0, 1.0, 0.5, -0.25, 2.0, 10.0, -10.0, 11.0, 1e-9]), min_size=2, max_size=2),
       st.floats(-20, 20, allow_nan=False))
@example([0.5, 1.0], 1e-7)          # rounds to 0 on writing: left out, not written as a 0 the range refuses
def test_poses_write_then_read_round_trips_or_refuses(rng, weight):
    from keyshape.base.errors import InputError
    from keyshape.base.formats.poses import read_poses, write_poses
    lib = _toy_poses()
    lib["range"] = rng
    for reg in lib["regions"].values():
        reg["neutral"] = {}
        reg["keys"] = {k: {} for k in reg["keys"]}
    lib["regions"]["mouth"]["keys"]["mouth_0"]["jawOpen"] = weight
    with tempfile.TemporaryDirectory(prefix="rt-p-") as tmp:
        d = Path(tmp)
        write_poses(d / "p.json", lib)
        lo, hi = rng
        w = round(weight, 5)
        valid = -10 <= lo < hi <= 10 and (w == 0 or lo - 1e-9 <= w <= hi + 1e-9)
        try:
            back = read_poses(d / "p.json", ["jawOpen", "mouthSmile_L", "eyeBlink_L"])
        except InputError as exc:
            assert "\n" not in str(exc) and not valid, str(exc)
            return
        assert valid
        assert back["range"] == [float(x) for x in rng]
        got = back["regions"]["mouth"]["keys"]["mouth_0"].get("jawOpen", 0.0)
        assert got == pytest.approx(round(weight, 5), abs=1e-9)


# ------------------------------------------------------------------ the label page's request bodies
def _fuzz_label_page(n: int) -> None:
    from keyshape.base.formats.labels import read_pts
    from keyshape.tracker.labelling import server as srv_mod
    from label_helpers import make_folder
    from server_helpers import request, serving

    with tempfile.TemporaryDirectory(prefix="fuzz-label-") as tmp:
        d = Path(tmp)
        folder = make_folder(d)
        pts = read_pts(folder / "000005.pts")
        seed = json.dumps({"points": np.round(pts, 2).tolist()}).encode()
        with serving(srv_mod.LabelServer(folder, 0)) as server:

            @settings(max_examples=n, deadline=None, database=None, derandomize=n < 1000,
                      suppress_health_check=list(HealthCheck))
            @given(mutated(seed))
            def run(body):
                status, reply = request(server, "PUT", "/api/points/000005.pts", body)
                assert status == 200 or 400 <= status < 500, (status, reply)   # never a 5xx, always an answer
                p = read_pts(folder / "000005.pts")                              # what the page wrote reads back
                assert np.isfinite(p).all() and p.shape == pts.shape

            run()


def test_label_page_request_fuzz():
    _fuzz_label_page(120)


@pytest.mark.slow
def test_label_page_request_fuzz_long():
    _fuzz_label_page(1500)
