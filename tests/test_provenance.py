"""Provenance (issue 27): the frame size travels in the model and the tracks, and a video of another
size is refused with one line (track, select --sheet --video); key sets carry their model's
fingerprint; POSES.json carries its key set's."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from keyshape.cli import main


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err and "\n" not in err and "Traceback" not in err, err
    return err


def _resized(src: Path, dst: Path, scale: float) -> Path:
    from keyshape.base.formats.video import VideoReader, video_writer
    r = VideoReader(src)
    size = (int(r.info.width * scale), int(r.info.height * scale))
    with video_writer(dst, r.info.fps, size) as wr:
        for _, img in r:
            wr.write(cv2.resize(img, size))
    return dst


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("prov")
    assert main(["synth", "video", str(d / "foot"), "--frames", "24", "--size", "160x120", "--labels", "8"]) == 0
    assert main(["train", str(d / "foot" / "video.mp4"), "--labels", str(d / "foot" / "labels"), "--morphs", "10",
                 "-o", str(d / "model.npz")]) == 0
    assert main(["track", str(d / "foot" / "video.mp4"), "--model", str(d / "model.npz"), "-o",
                 str(d / "tracks.csv"), "--quiet"]) == 0
    small = _resized(d / "foot" / "video.mp4", d / "small.mp4", 0.5)
    return d, small


def test_the_model_and_the_tracks_record_the_frame_size(trained):
    from keyshape.base.formats.model import read_model
    from keyshape.base.formats.tracks import read_tracks
    d, _ = trained
    assert read_model(d / "model.npz").state["image_size"] == [160, 120]
    assert read_tracks(d / "tracks.csv").meta["image_size"] == [160, 120]


def test_track_refuses_a_video_of_another_size(trained, tmp_path, capsys):
    d, small = trained
    out = tmp_path / "t.csv"
    assert main(["track", str(small), "--model", str(d / "model.npz"), "-o", str(out), "--quiet"]) == 2
    err = one_line(capsys)
    assert "80x60" in err and "160x120" in err and "small.mp4" in err
    assert list(tmp_path.iterdir()) == []
    from keyshape import api
    from keyshape.base.errors import InputError
    with pytest.raises(InputError, match="trained on 160x120"):
        api.track(small, api.AppearanceModel.load(d / "model.npz"))


def test_a_model_without_a_recorded_size_still_tracks(trained, tmp_path):
    """Models trained before the size was recorded load and track any video, as before."""
    from keyshape.base.formats.model import read_model, write_model
    d, small = trained
    mf = read_model(d / "model.npz")
    mf.state.pop("image_size")
    write_model(tmp_path / "old.npz", mf)
    assert main(["track", str(small), "--model", str(tmp_path / "old.npz"), "-o", str(tmp_path / "t.csv"),
                 "--quiet"]) == 0


@pytest.mark.parametrize("bad", [[0, 120], [160], "160x120", [160.5, 120], [1e9, 1]])
def test_a_bad_recorded_size_is_one_line(trained, tmp_path, capsys, bad):
    from keyshape.base.formats.model import read_model, write_model
    d, _ = trained
    mf = read_model(d / "model.npz")
    mf.state["image_size"] = bad
    write_model(tmp_path / "bad.npz", mf)
    assert main(["track", str(d / "foot" / "video.mp4"), "--model", str(tmp_path / "bad.npz"), "-o",
                 str(tmp_path / "t.csv"), "--quiet"]) == 2
    assert "image_size" in one_line(capsys)


def test_select_sheet_refuses_a_video_of_another_size(trained, tmp_path, capsys):
    d, small = trained
    args = ["select", str(d / "tracks.csv"), "-k", "2", "--region", "mouth", "-o", str(tmp_path / "k.json"),
            "--sheet", str(tmp_path / "s.png"), "--video"]
    assert main(args + [str(small)]) == 2
    err = one_line(capsys)
    assert "80x60" in err and "160x120" in err
    assert list(tmp_path.iterdir()) == []
    assert main(args + [str(d / "foot" / "video.mp4")]) == 0


# --------------------------------------------------------------------------- key sets carry their model
def test_api_key_sets_carry_the_model_fingerprint_and_decompose_checks_it(trained, tmp_path, capsys):
    from keyshape import api
    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import read_keys_source
    d, _ = trained
    tracks = api.read_tracks(d / "tracks.csv")
    keys = api.select(tracks, 2, "greedy", "mouth")            # a str region is one region, not letters
    assert [rk.region for rk in keys.regions] == ["mouth"]
    keys.save(tmp_path / "k.json")
    assert read_keys_source(tmp_path / "k.json")["model"] == tracks.meta["model"]
    assert api.Keys.load(tmp_path / "k.json").source["model"] == tracks.meta["model"]
    other = api.read_tracks(d / "tracks.csv")
    other.meta = {**other.meta, "model": "sha256:0000000000000000"}
    with pytest.raises(InputError, match="another tracker model"):
        api.decompose(other, keys)
    api.decompose(other, keys, allow_foreign_keys=True)
    from keyshape.base.formats.tracks import write_tracks
    write_tracks(tmp_path / "other.csv", other)
    assert main(["decompose", str(tmp_path / "other.csv"), "--keys", str(tmp_path / "k.json"), "-o",
                 str(tmp_path / "w.csv")]) == 2
    assert "another tracker model" in one_line(capsys)


# --------------------------------------------------------------------------- API arguments
@pytest.mark.parametrize("call, message", [
    (lambda api: api.track("v.mp4", None), "model: expected a fitted AppearanceModel or a model file, got NoneType"),
    (lambda api: api.select("x", 2), "got the path 'x'"),
    (lambda api: api.select([], 2), "tracks must be Tracks"),
    (lambda api: api.decompose("tracks.csv", None), "tracks: expected Tracks"),
    (lambda api: api.retarget("weights.csv", "targets"), "weights: expected Weights"),
    (lambda api: api.retarget(api.Weights([], ["mouth_0"], np.zeros((0, 1))), "targets"), "no frames"),
    (lambda api: api.Weights([0.5, 1.5], ["mouth_0"], [[0.1], [0.2]]), "whole frame numbers"),
])
def test_api_arguments_of_the_wrong_kind_are_one_line(call, message):
    from keyshape import api
    from keyshape.base.errors import InputError
    with pytest.raises(InputError, match=None) as exc:
        call(api)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_decompose_with_a_path_for_keys(trained):
    from keyshape import api
    from keyshape.base.errors import InputError
    d, _ = trained
    with pytest.raises(InputError, match="keys: expected Keys"):
        api.decompose(api.read_tracks(d / "tracks.csv"), "keys.json")


@pytest.mark.parametrize("frames, values, message", [
    ([0, 1, 2], [[0.1], [np.nan], [0.2]], "nan"),
    ([0, 1, 2], [[0.1], [np.inf], [0.2]], "inf"),
    ([0, 1, 2], [[0.1], [2e6], [0.2]], "2e+06"),
    ([2, 1, 0], [[0.1], [0.1], [0.2]], "out of order"),
    ([0, 0, 1], [[0.1], [0.1], [0.2]], "repeated"),
    ([0, 2, 3], [[0.1], [0.1], [0.2]], "jump"),
    ([], np.zeros((0, 1)), "no frames"),
])
def test_the_api_never_writes_weights_its_reader_refuses(tmp_path, frames, values, message):
    from keyshape import api
    from keyshape.base.errors import InputError
    w = api.Weights(np.asarray(frames, dtype=np.int64), ["mouth_0"], np.asarray(values, dtype=float))
    with pytest.raises(InputError) as exc:
        w.save(tmp_path / "w.csv")
    assert message in str(exc.value) and "nothing written" in str(exc.value) and "w.csv" in str(exc.value)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- pose ranges and rig names
@pytest.mark.parametrize("rng, message", [
    ([-1e9, 1e9], "range [-1e+09, 1e+09]"), ([1.0, 0.0], "low < high"), ([0.0, "1"], "expected [low, high]"),
    ([0.0], "expected [low, high]"), ("0,1", "expected [low, high]"), ([0.0, 11.0], "<= 10"),
])
def test_a_bad_pose_range_is_refused(tmp_path, capsys, rng, message):
    from test_rig_poses import _setup
    rig, _ = _setup(tmp_path)
    p = tmp_path / "poses.json"
    d = json.loads(p.read_text())
    d["range"] = rng
    p.write_text(json.dumps(d))
    out = tmp_path / "curves.csv"
    assert main(["retarget", str(tmp_path / "w.csv"), "--poses", str(p), "--rig", str(rig), "-o", str(out)]) == 2
    err = one_line(capsys)
    assert message in err and str(p) in err
    assert not out.exists()


def test_a_rig_with_case_duplicate_shape_names_is_refused(tmp_path, capsys):
    from test_rig_poses import _setup
    rig, _ = _setup(tmp_path)
    first = sorted(p for p in rig.glob("*.obj") if p.stem != "neutral")[0]
    twin = rig / (first.stem.swapcase() + ".obj")
    n = len(list(rig.glob("*.obj")))
    twin.write_bytes(first.read_bytes())
    if len(list(rig.glob("*.obj"))) == n:                       # case-insensitive file system: nothing to test
        pytest.skip("case-insensitive file system")
    out = tmp_path / "curves.csv"
    assert main(["retarget", str(tmp_path / "w.csv"), "--poses", str(tmp_path / "poses.json"), "--rig", str(rig),
                 "-o", str(out)]) == 2
    err = one_line(capsys)
    assert "differ only by case" in err and first.name in err and twin.name in err
    assert not out.exists()


# --------------------------------------------------------------------------- C3D cut short
def test_a_c3d_cut_short_warns_with_both_counts(tmp_path, capsys):
    from keyshape.base.formats.markers import Markers, read_c3d, write_c3d
    m = Markers(np.random.default_rng(0).normal(size=(200, 5, 3)) * 100, [f"m{i}" for i in range(5)], 120.0, "mm")
    write_c3d(tmp_path / "a.c3d", m)
    assert read_c3d(tmp_path / "a.c3d").warnings == []
    data = (tmp_path / "a.c3d").read_bytes()
    (tmp_path / "cut.c3d").write_bytes(data[: len(data) // 2])
    cut = read_c3d(tmp_path / "cut.c3d")
    assert 0 < cut.n_frames < 200
    assert len(cut.warnings) == 1 and f"announces 200 frames but the file holds {cut.n_frames}" in cut.warnings[0]


# --------------------------------------------------------------------------- POSES.json names its key set
def test_poses_record_their_key_set_and_refuse_another_models_tracks(tmp_path, capsys):
    from keyshape.base.files import sha256_file
    from keyshape.base.formats.keys import write_keys
    from keyshape.base.formats.tracks import Tracks, write_tracks
    from test_rig_poses import TRUE, actor_keys, write_toy_rig
    rig, lm = write_toy_rig(tmp_path / "rig")
    write_keys(tmp_path / "keys.json", "contours48", 48, actor_keys(TRUE),
               source={"model": "sha256:aaaaaaaaaaaaaaaa", "scheme": "contours48"})
    assert main(["pose", str(tmp_path / "keys.json"), "--rig", str(rig), "--landmarks", str(lm),
                 "-o", str(tmp_path / "poses.json")]) == 0
    keys = json.loads((tmp_path / "poses.json").read_text())["keys"]
    assert keys["sha256"] == sha256_file(tmp_path / "keys.json") and keys["model"] == "sha256:aaaaaaaaaaaaaaaa"
    from keyshape.base.formats.weights import write_weights
    write_weights(tmp_path / "w.csv", np.arange(3), list(TRUE), np.full((3, len(TRUE)), 0.5))
    rng = np.random.default_rng(0)
    t = Tracks(np.arange(3), np.arange(3) / 30.0, np.ones(3), np.ones(3, bool), rng.uniform(50, 100, (3, 48, 2)),
               np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (3, 1, 1)), {"model": "sha256:bbbbbbbbbbbbbbbb"})
    write_tracks(tmp_path / "t.csv", t)
    out = tmp_path / "curves.csv"
    assert main(["retarget", str(tmp_path / "w.csv"), "--poses", str(tmp_path / "poses.json"), "--rig", str(rig),
                 "--tracks", str(tmp_path / "t.csv"), "-o", str(out)]) == 2
    err = one_line(capsys)
    assert "another tracker model" in err and "poses.json" in err
    assert not out.exists()


def test_preview_refuses_a_video_of_another_size_than_the_tracks(tmp_path, capsys):
    from keyshape.base.formats.tracks import write_tracks
    from keyshape.base.formats.video import video_writer
    from keyshape.base.formats.weights import write_weights
    from toy import toy_tracks
    from test_rig_poses import SHAPES, write_toy_rig
    rig, _ = write_toy_rig(tmp_path / "rig")
    tr = toy_tracks(30, rng=1)
    tr.meta = {"model": "sha256:aaaaaaaaaaaaaaaa", "scheme": "contours48", "image_size": [320, 240]}
    write_tracks(tmp_path / "t.csv", tr)
    with video_writer(tmp_path / "v.mp4", 10, (160, 120)) as wr:
        for i in range(30):
            wr.write(np.full((120, 160, 3), 8 * i, np.uint8))
    write_weights(tmp_path / "c.csv", np.arange(30), list(SHAPES), np.zeros((30, len(SHAPES))))
    sheet = tmp_path / "s.jpg"
    assert main(["preview", str(tmp_path / "v.mp4"), "--tracks", str(tmp_path / "t.csv"), "--curves",
                 str(tmp_path / "c.csv"), "--rig", str(rig), "--sheet", str(sheet)]) == 2
    err = one_line(capsys)
    assert "160x120" in err and "320x240" in err
    assert not sheet.exists()


# --------------------------------------------------------------------------- labels know their footage (issue 37)
def test_labels_of_another_video_or_size_are_refused_before_training(tmp_path, capsys):
    from keyshape.base.formats.labels import FOOTAGE_FILE, read_footage
    for name, extra in (("a", []), ("b", ["--seed", "5"]), ("small", ["--size", "160x120"])):
        assert main(["synth", "video", str(tmp_path / name), "--frames", "12", "--labels", "8", "--size", "192x144",
                     *extra]) == 0
    rec = read_footage(tmp_path / "a" / "labels")
    assert rec["width"] == 192 and rec["n_frames"] == 12 and len(rec["sha256"]) == 64
    capsys.readouterr()
    labels = str(tmp_path / "a" / "labels")
    for video, phrase in (("small", "160x120"), ("b", "another video")):
        rc = main(["train", str(tmp_path / video / "video.mp4"), "--labels", labels, "-o", str(tmp_path / "m.npz")])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and phrase in err and "labels" in err and "\n" not in err, err
        assert not (tmp_path / "m.npz").exists()
    rc = main(["train", str(tmp_path / "small" / "video.mp4"), "--labels", labels, "--labels-from-other-video",
               "-o", str(tmp_path / "m.npz")])
    assert rc == 2 and "160x120" in capsys.readouterr().err          # another size: never meaningful
    (tmp_path / "a" / "labels" / FOOTAGE_FILE).unlink()                  # an older folder: trains, says so
    assert main(["train", str(tmp_path / "a" / "video.mp4"), "--labels", labels,
                 "-o", str(tmp_path / "m.npz")]) == 0
    err = capsys.readouterr().err
    assert f"no {FOOTAGE_FILE}" in err
