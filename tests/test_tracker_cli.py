"""``keyshape train`` / ``keyshape track`` end to end on a small made-up video, and their bad-input errors."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.cli import main
from tracker.io import read_tracks, write_labels, write_pts
from tracker.video import video_writer

from tests.test_tracker import footage  # noqa: F401  (module fixture reused)

LABELLED = [0, 2, 4, 6, 8]


@pytest.fixture(scope="module")
def files(footage, tmp_path_factory):  # noqa: F811
    frames, labels = footage
    d = tmp_path_factory.mktemp("cli")
    video = d / "clip.avi"
    with video_writer(video, 10.0, (frames.shape[2], frames.shape[1])) as w:
        for f in frames:
            w.write(np.repeat(f[:, :, None], 3, axis=2))
    write_labels(d / "labels", LABELLED, labels[LABELLED])
    model = d / "model.npz"
    assert main(["train", str(video), "--labels", str(d / "labels"), "-o", str(model)]) == 0
    return d, video, model, labels


def test_train_and_track(files, capsys):
    d, video, model, labels = files
    out = d / "tracks.csv"
    rc = main(["track", str(video), "--model", str(model), "-o", str(out), "--overlay", str(d / "over.avi"),
               "--quiet"])
    assert rc == 0
    tr = read_tracks(out)
    assert tr.n_frames == len(labels) and tr.success.all()
    err = np.linalg.norm(tr.points - labels, axis=-1).mean(1)
    assert err[LABELLED].max() < 1.5 and err.mean() < 2.0, err
    assert (d / "over.avi").is_file()
    assert "10 frames, 0 lost" in capsys.readouterr().out


def test_video_that_does_not_open(files, tmp_path, capsys):
    d, video, model, _ = files
    bad = tmp_path / "notavideo.mp4"
    bad.write_text("hello")
    assert main(["track", str(bad), "--model", str(model), "-o", str(tmp_path / "t.csv")]) == 2
    assert "notavideo.mp4: cannot open as a video" in capsys.readouterr().err
    assert not (tmp_path / "t.csv").exists()


def test_truncated_video_tracks_up_to_the_break(files, tmp_path, capsys):
    d, video, model, _ = files
    data = video.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) * 6 // 10])
    out = tmp_path / "t.csv"
    rc = main(["track", str(cut), "--model", str(model), "-o", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    tr = read_tracks(out)
    assert 0 < tr.n_frames < 10
    assert "cut.avi ended after" in err and "truncated" in err


def test_label_count_mismatch_names_the_file(files, tmp_path, capsys):
    d, video, _, labels = files
    lab = tmp_path / "labels"
    write_labels(lab, [0, 2], labels[[0, 2]])
    write_pts(lab / "000004.pts", labels[4][:40])
    assert main(["train", str(video), "--labels", str(lab), "-o", str(tmp_path / "m.npz")]) == 2
    assert "000004.pts: 40 points, expected 48" in capsys.readouterr().err


def test_labels_past_the_end(files, tmp_path, capsys):
    d, video, _, labels = files
    lab = tmp_path / "labels"
    write_labels(lab, [0, 2, 50], labels[[0, 2, 4]])
    assert main(["train", str(video), "--labels", str(lab), "-o", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err
    assert "labels" in err and "[50]" in err and "10 frames" in err


def test_zero_frame_video(files, tmp_path, capsys):
    d, _, model, _ = files
    empty = tmp_path / "empty.avi"
    with video_writer(empty, 10.0, (320, 240)):
        pass
    assert main(["track", str(empty), "--model", str(model), "-o", str(tmp_path / "t.csv"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "empty.avi" in err and ("no decodable frames" in err or "cannot open" in err)
    assert not (tmp_path / "t.csv").exists()


def test_model_from_another_scheme_or_corrupt(files, tmp_path, capsys):
    d, video, model, _ = files
    assert main(["track", str(video), "--model", str(model), "--scheme", "ibug68",
                 "-o", str(tmp_path / "t.csv")]) == 2
    assert "model.npz: model was trained in scheme 'contours48'" in capsys.readouterr().err
    bad = tmp_path / "broken.npz"
    bad.write_bytes(model.read_bytes()[:300])
    assert main(["track", str(video), "--model", str(bad), "-o", str(tmp_path / "t.csv")]) == 2
    assert "broken.npz: not a keyshape model file" in capsys.readouterr().err


def test_ctrl_c_keeps_the_frames_tracked_so_far(files, tmp_path, monkeypatch, capsys):
    from tracker.fitting import Tracker

    d, video, model, _ = files
    real_step = Tracker.step

    def step(self, frame, index=0):
        if index == 4:
            raise KeyboardInterrupt
        return real_step(self, frame, index)

    monkeypatch.setattr(Tracker, "step", step)
    out = tmp_path / "t.csv"
    assert main(["track", str(video), "--model", str(model), "-o", str(out), "--smooth", "savgol", "--quiet"]) == 130
    assert "interrupted: tracks written for frames 0-3 only" in capsys.readouterr().out
    tr = read_tracks(out)
    np.testing.assert_array_equal(tr.frame, [0, 1, 2, 3])
