"""One pipeline: every stage through the Python API with no options gives the files the command gives with
no options (to the files' precision), the sculpted-targets path and the rig path (pose, the rig's curves,
Live Link, .glb, preview) alike, on a small synthetic take and a small rig made from the shipped
ICT-FaceKit subset."""
from __future__ import annotations

import filecmp
import json
from pathlib import Path

import numpy as np
import pytest

from keyshape.cli import main

K = 4
#: the rig's shapes (of the shipped ICT-FaceKit subset's 53: what the test proves holds for any rig)
RIG_SHAPES = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R",
              "mouthFunnel"]


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    from keyshape.data_synth.library import ict_subset_rig
    from synth_library import grid_targets
    from keyshape.data_synth.video import synthesize

    d = tmp_path_factory.mktemp("pipeline")
    synthesize(d / "foot", frames=40, seed=5, labels=12)
    grid_targets(d / "targets", {"mouth": K, "eyes": K, "pupils": K})
    ict_subset_rig(d / "rig", names=RIG_SHAPES)
    return d


def json_without(path, *keys) -> dict:
    data = json.loads(Path(path).read_text())
    for k in keys:
        data.pop(k, None)
    return data


def same(a, b) -> bool:
    return filecmp.cmp(a, b, shallow=False)


def test_every_stage_api_and_command_with_no_options_give_the_same_files(take, tmp_path, capsys):
    from keyshape import api

    foot, c, p = take / "foot", tmp_path / "cmd", tmp_path / "api"
    c.mkdir()
    p.mkdir()
    video, rig, lm = foot / "video.mp4", take / "rig", take / "rig_landmarks.json"

    # train, track
    assert main(["train", str(video), "--labels", str(foot / "labels"), "-o", str(c / "model.npz")]) == 0
    model = api.train(video, foot / "labels")
    model.save(p / "model.npz")
    with np.load(c / "model.npz") as x, np.load(p / "model.npz") as y:
        assert sorted(x.files) == sorted(y.files)
        for f in x.files:
            np.testing.assert_array_equal(x[f], y[f], err_msg=f)
    assert main(["track", str(video), "--model", str(c / "model.npz"), "-o", str(c / "tracks.csv"), "--quiet"]) == 0
    tracks = api.track(video, api.AppearanceModel.load(c / "model.npz"))
    api.write_tracks(p / "tracks.csv", tracks)
    assert same(c / "tracks.csv", p / "tracks.csv")
    tracks = api.read_tracks(c / "tracks.csv")         # what the later commands read

    # select, decompose: the same defaults (greedy, the actor's neutral, near-duplicates dropped; smooth, ridge)
    assert main(["select", str(c / "tracks.csv"), "-k", str(K), "-o", str(c / "keys.json")]) == 0
    keys = api.select(tracks, K)
    keys.save(p / "keys.json")
    assert json_without(c / "keys.json", "source") == json_without(p / "keys.json", "source")
    keys = api.Keys.load(c / "keys.json")
    assert main(["decompose", str(c / "tracks.csv"), "--keys", str(c / "keys.json"),
                 "-o", str(c / "weights.csv")]) == 0
    api.decompose(tracks, keys).save(p / "weights.csv")
    assert same(c / "weights.csv", p / "weights.csv")
    weights = api.Weights.load(c / "weights.csv")

    # sculpted targets, one per key (the tracks are an input, not an option)
    targets = take / "targets"
    assert all((targets / f"{n}.obj").is_file() for n in weights.names), weights.names
    anim = api.retarget(weights, targets, tracks=tracks)
    for name in ("animation.glb", "curves.csv"):
        assert main(["retarget", str(c / "weights.csv"), "--targets", str(targets),
                     "--tracks", str(c / "tracks.csv"), "-o", str(c / name)]) == 0
        anim.export(p / name)
        assert same(c / name, p / name), name

    # the rig: pose, the rig's curves, Live Link, .glb, preview
    assert main(["pose", str(c / "keys.json"), "--rig", str(rig), "--landmarks", str(lm),
                 "-o", str(c / "poses.json")]) == 0
    lib = api.pose(keys, rig, landmarks=lm)
    lib.save(p / "poses.json")
    assert json_without(c / "poses.json", "keys") == json_without(p / "poses.json", "keys")
    lib = api.PoseLibrary.load(c / "poses.json")
    ranim = api.retarget(weights, options=api.RetargetOptions(landmarks=str(lm)), poses=lib, rig=rig, tracks=tracks)
    for name, extra in (("curves.csv", []), ("livelink.csv", ["--livelink"]), ("rig.glb", [])):
        assert main(["retarget", str(c / "weights.csv"), "--poses", str(c / "poses.json"), "--rig", str(rig),
                     "--landmarks", str(lm), "--tracks", str(c / "tracks.csv"), *extra, "-o", str(c / name)]) == 0
        ranim.export(p / name, livelink=bool(extra))
        assert same(c / name, p / name), name
    assert main(["preview", str(video), "--tracks", str(c / "tracks.csv"), "--curves", str(c / "curves.csv"),
                 "--rig", str(rig), "--frames", "0:6", "--size", "96", "--sheet", str(c / "sheet.png")]) == 0
    api.preview(video, tracks, ranim, sheet=p / "sheet.png", options=api.PreviewOptions(frames="0:6", size=96))
    assert same(c / "sheet.png", p / "sheet.png")


def test_the_take_frame_rate_travels_with_the_weights(tmp_path, capsys):
    """WEIGHTS.csv carries the take's frame rate in its ``time`` column: ``retarget`` without ``--tracks``
    keeps a 24 fps take at 24 fps (not 30); an older file with the rate in a leading comment reads at its
    rate, and one with neither still reads, at 30 fps."""
    import pygltflib

    from keyshape import api
    from keyshape.base.formats.weights import read_weights, read_weights_fps
    from synth_library import grid_targets

    regions = grid_targets(tmp_path / "targets", {"mouth": 2})
    w = api.Weights(np.arange(5), ["mouth_0", "mouth_1"], np.full((5, 2), 0.5), fps=24.0)
    w.save(tmp_path / "w.csv")
    assert (tmp_path / "w.csv").read_text().startswith("frame,time,mouth_0,mouth_1,interpolated\n0,0.000000,")
    assert read_weights_fps(tmp_path / "w.csv") == 24.0 and api.Weights.load(tmp_path / "w.csv").fps == 24.0
    np.testing.assert_array_equal(read_weights(tmp_path / "w.csv").weights, w.values)
    (tmp_path / "r.json").write_text(json.dumps(regions))
    assert main(["retarget", str(tmp_path / "w.csv"), "--targets", str(tmp_path / "targets"),
                 "-o", str(tmp_path / "a.glb")]) == 0
    assert "at 24 fps" in capsys.readouterr().out
    assert pygltflib.GLTF2().load(str(tmp_path / "a.glb")).scenes[0].extras["fps"] == 24.0
    assert api.retarget(api.Weights.load(tmp_path / "w.csv"), tmp_path / "targets").fps == 24.0
    commented = tmp_path / "commented.csv"          # the form keyshape wrote before the time column
    commented.write_text("# keyshape weights, fps=24\nframe,mouth_0,mouth_1\n0,0.5,0.5\n1,0.5,0.5\n")
    assert read_weights_fps(commented) == 24.0 and read_weights(commented).names == ["mouth_0", "mouth_1"]
    old = tmp_path / "old.csv"
    old.write_text("frame,mouth_0,mouth_1\n0,0.5,0.5\n1,0.5,0.5\n")
    assert read_weights_fps(old) is None and api.Weights.load(old).fps is None
    assert main(["retarget", str(old), "--targets", str(tmp_path / "targets"), "-o", str(tmp_path / "b.csv")]) == 0
    assert "at 30 fps" in capsys.readouterr().out


def test_a_parsed_rig_is_cached_by_content_and_a_damaged_cache_is_rebuilt(tmp_path, monkeypatch):
    from keyshape.data_synth.library import ict_subset_rig
    from keyshape.retarget.rig.model import cache_dir, load_rig

    monkeypatch.setenv("KEYSHAPE_CACHE", str(tmp_path / "cache"))
    rig, _ = ict_subset_rig(tmp_path / "rig", names=["jawOpen", "eyeBlink_L", "mouthSmile_L"])
    parsed = load_rig(rig, cache=False)
    first = load_rig(rig)
    files = list(cache_dir().glob("*.npz"))
    assert len(files) == 1 and not list(cache_dir().glob(".*partial*"))
    cached = load_rig(rig)
    for r in (first, cached):
        assert r.names == parsed.names == ["eyeBlink_L", "jawOpen", "mouthSmile_L"]
        np.testing.assert_array_equal(r.deltas, parsed.deltas)
        np.testing.assert_array_equal(r.neutral, parsed.neutral)
        assert len(r.mesh.polygons) == len(parsed.mesh.polygons)
        assert all(np.array_equal(a, b) for a, b in zip(r.mesh.polygons, parsed.mesh.polygons))
    assert load_rig(rig, with_mesh=False).mesh is None
    # damaged: a non-finite value, then a truncated file: parsed again, the cache rewritten
    with np.load(files[0]) as d:
        data = dict(d)
    data["deltas"][0, 0, 0] = np.nan
    with open(files[0], "wb") as f:
        np.savez(f, **data)
    np.testing.assert_array_equal(load_rig(rig).deltas, parsed.deltas)
    files[0].write_bytes(files[0].read_bytes()[:1000])
    np.testing.assert_array_equal(load_rig(rig).deltas, parsed.deltas)
    with np.load(files[0]) as d:
        assert np.isfinite(d["deltas"]).all()
    # an edited shape is another rig: parsed, cached beside
    (rig / "jawOpen.obj").write_text((rig / "eyeBlink_L.obj").read_text())
    np.testing.assert_array_equal(load_rig(rig).deltas[1], parsed.deltas[0])
    assert len(list(cache_dir().glob("*.npz"))) == 2
