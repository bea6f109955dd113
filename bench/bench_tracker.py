"""Tracking speed against plain decoding of the same video, measured in the same run (issues 3, 26).

Synthesises 640x480 footage (or takes ``--video`` with ``--labels``), trains on
its labels (timed) and reports frames/s of decode-only, of decode + tracking
(decoding in a background thread, the default) and their ratio, and the same
without the decode thread, and the CPU time per frame of each (``time.process_time``), and on
synthetic footage the track's NME against the true points;
then the tracker step's thread CPU time on the decoded frames, the compiled kernels' first-run compile time (a fresh process with an empty numba cache,
then one that loads them from it), and the command-level ratio: ``keyshape track`` run as a command (imports and model loading
included) against decoding the same file, with one job and with ``--jobs 2`` (two worker processes
tracking halves of the video, stitched). The load average is printed beside the figures.
Prints ratios, never asserts times.

    PYTHONPATH=. python bench/bench_tracker.py [--frames 600] [--video V --labels DIR --scheme S]
    PYTHONPATH=. python bench/bench_tracker.py --frames 6000        # the issue's command-level figure
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from footage import add_footage_args, footage


def _decode_rate(video, **reader) -> tuple[float, float]:
    """Frames/s and CPU seconds per frame of decoding ``video`` (the better of two passes); ``reader``:
    :class:`VideoReader` options (none: plain BGR decoding, the issue's baseline)."""
    from keyshape.base.formats.video import VideoReader

    best = (0.0, float("inf"))
    for _ in range(2):
        t0, c0 = time.perf_counter(), time.process_time()
        n = sum(1 for _ in VideoReader(video, **reader))
        best = (max(best[0], n / (time.perf_counter() - t0)), min(best[1], (time.process_time() - c0) / n))
    return best


def _step_time(video, model, n_frames: int = 300, reps: int = 3) -> float:
    """Thread CPU seconds per frame of ``Tracker.step`` on the same decoded frames (best of ``reps``)."""
    from keyshape.base.formats.video import VideoReader
    from keyshape.tracker.fitting import Tracker, single_threaded

    frames = []
    for i, f in VideoReader(video, gray=True, luma=True):      # the frames the tracker is given
        if i >= n_frames:
            break
        frames.append(f)
    best = float("inf")
    with single_threaded():
        for _ in range(reps):
            tr = Tracker(model)
            c0 = time.thread_time()
            for i, f in enumerate(frames):
                tr.step(f, i)
            best = min(best, (time.thread_time() - c0) / len(frames))
    return best


_FIRST_STEPS = """
import itertools, sys, time
from keyshape.base.formats.video import VideoReader
from keyshape.tracker.eigenpoints import AppearanceModel
from keyshape.tracker.fitting import Tracker
model = AppearanceModel.load(sys.argv[1])
frames = [f for _, f in itertools.islice(VideoReader(sys.argv[2], gray=True, luma=True), 2)]
tracker = Tracker(model)
t0 = time.perf_counter()
tracker.step(frames[0])
t1 = time.perf_counter()
tracker.step(frames[1])
print(t1 - t0, time.perf_counter() - t1)
"""


def _compile_time(model_path, video) -> tuple[float, float, float]:
    """Seconds of a fresh process's first ``Tracker.step`` with an empty numba cache (the kernels compiled),
    the same with the cache that run wrote (loaded), and a second step's (neither)."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        runs = [subprocess.run([sys.executable, "-c", _FIRST_STEPS, str(model_path), str(video)], env=env,
                               check=True, capture_output=True, text=True).stdout.split() for _ in range(2)]
    return float(runs[0][0]), float(runs[1][0]), float(runs[1][1])


def _nme(tracks, truth, scheme) -> float:
    """Mean over frames of the mean point-to-point error of ``tracks`` against ``truth`` over the true
    inter-ocular distance (``bench/synth_accuracy.py``'s NME; lost frames left out)."""
    import numpy as np
    from keyshape.base.formats.tracks import read_tracks

    got, want = read_tracks(tracks).points, read_tracks(truth).points
    d = np.linalg.norm(got - want, axis=-1).mean(1) / scheme.interocular_distance(want)
    return float(np.nanmean(d))


def main() -> None:
    ap = argparse.ArgumentParser()
    add_footage_args(ap, frames=600)
    args = ap.parse_args()
    from keyshape.tracker.commands import fit_model, track_video
    from keyshape.tracker.defaults import TrackOptions
    from keyshape.base.formats.video import VideoReader
    from keyshape.tracker.fitting import Tracker

    with tempfile.TemporaryDirectory() as tmp:
        video, labels, truth = footage(args, tmp)
        t0 = time.perf_counter()
        model = fit_model(video, labels, args.scheme)
        t_train = time.perf_counter() - t0
        load0 = os.getloadavg()[0]
        decode, cpu_decode = _decode_rate(video)
        info = VideoReader(video).info
        n = info.n_frames
        # the kernels compiled or loaded before any timed run (a stale numba cache would add its compile time)
        Tracker(model).step(next(iter(VideoReader(video, gray=True, luma=True)))[1])
        c0 = time.process_time()
        summ = track_video(video, model, Path(tmp) / "tracks.csv", show_progress=False)
        cpu_thread = (time.process_time() - c0) / summ.n_frames
        c0 = time.process_time()
        summ0 = track_video(video, model, Path(tmp) / "tracks0.csv", options=TrackOptions(decode_thread=False),
                            show_progress=False)
        cpu_plain = (time.process_time() - c0) / summ0.n_frames
        step = _step_time(video, model)
        # the command as a user runs it: a fresh process, imports and the model file included
        model_path = Path(tmp) / "model.npz"
        model.save(model_path)
        compiled, cached, plain = _compile_time(model_path, video)
        t_cmd = {}
        for jobs in (1, 2):      # one process, and two worker processes on chunks of the video (--jobs 2)
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "keyshape", "track", str(video), "--model", str(model_path), "-o",
                            str(Path(tmp) / f"tracks_cmd{jobs}.csv"), "--quiet", "--jobs", str(jobs)], check=True,
                           stdout=subprocess.DEVNULL)
            t_cmd[jobs] = time.perf_counter() - t0
        decode2, cpu_decode2 = _decode_rate(video)
        decode, cpu_decode = max(decode, decode2), min(cpu_decode, cpu_decode2)
        # what the tracker decodes: the luma plane alone where it gives the BGR's gray (VideoReader(luma=True))
        luma, cpu_luma = _decode_rate(video, gray=True, luma=True)
        luma_on = VideoReader(video, gray=True, luma=True).luma_table_ is not None
        load1 = os.getloadavg()[0]
        print(f"video {video.name}: {n} frames {info.width}x{info.height}; load average {load0:.2f} at the start, "
              f"{load1:.2f} at the end (2 cores: above 2 the figures are slowed by other work)")
        print(f"training on {len(model.train_poses_)} labels: {t_train:.1f} s")
        print(f"first run's compile time: a fresh process's first frame {compiled:.2f} s with an empty numba cache "
              f"(the kernels compiled), {cached:.2f} s with the cache it wrote, {1e3 * plain:.1f} ms for the next frame")
        if truth is not None:
            print(f"synthetic NME of the track (mean point error / inter-ocular distance): "
                  f"{_nme(Path(tmp) / 'tracks.csv', truth, model.scheme_):.5f}")
        print(f"decode only: {decode:.0f} frames/s; decode + track: {summ.fps:.0f} frames/s; "
              f"ratio {summ.fps / decode:.2f} (aim >= 0.5; floor 150 frames/s); lost {summ.n_lost}")
        print(f"without the decode thread: decode + track {summ0.fps:.0f} frames/s; ratio {summ0.fps / decode:.2f}")
        for jobs, t in t_cmd.items():
            print(f"command level: `keyshape track --jobs {jobs}` {t:.2f} s for {n} frames ({n / t:.0f} frames/s), "
                  f"decoding {n / decode:.2f} s: ratio {n / decode / t:.2f}; against decoding the luma alone "
                  f"({n / luma:.2f} s) {n / luma / t:.2f}")
        print(f"the tracker's frames: {'the luma plane alone' if luma_on else 'gray from BGR (no luma table)'}; "
              f"luma-only decode {luma:.0f} frames/s, {1e3 * cpu_luma:.3f} ms CPU a frame")
        # CPU seconds (time.process_time: all threads of this process) per frame: less sensitive than
        # frames/s to the other jobs of a shared machine
        print(f"CPU per frame: decode only {1e3 * cpu_decode:.3f} ms; decode + track {1e3 * cpu_thread:.3f} ms "
              f"(without the decode thread {1e3 * cpu_plain:.3f} ms); tracking alone about "
              f"{1e3 * (cpu_plain - cpu_decode):.3f} ms")
        print(f"tracker step, thread CPU per frame: {1e3 * step:.3f} ms")


if __name__ == "__main__":
    main()
