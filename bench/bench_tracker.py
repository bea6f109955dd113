"""Tracking speed against plain decoding of the same video, measured in the same run (issue 3).

Synthesises 640x480 footage (or takes ``--video`` with ``--labels``), trains on
its labels (timed) and reports frames/s of decode-only, of decode + tracking
(decoding in a background thread, the default) and their ratio, and the same
without the decode thread, and the CPU time per frame of each (``time.process_time``).
Prints ratios, never asserts times.

    PYTHONPATH=. python bench/bench_tracker.py [--frames 600] [--video V --labels DIR --scheme S]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from footage import add_footage_args, footage


def main() -> None:
    ap = argparse.ArgumentParser()
    add_footage_args(ap, frames=600)
    args = ap.parse_args()
    from keyshape.tracker.commands import track_video, train_model
    from keyshape.base.formats.video import VideoReader

    with tempfile.TemporaryDirectory() as tmp:
        video, labels, _ = footage(args, tmp)
        t0 = time.perf_counter()
        model, _ = train_model(video, labels, args.scheme)
        t_train = time.perf_counter() - t0
        t0, c0 = time.perf_counter(), time.process_time()
        n = sum(1 for _ in VideoReader(video))
        decode = n / (time.perf_counter() - t0)
        cpu_decode = (time.process_time() - c0) / n
        c0 = time.process_time()
        summ = track_video(video, model, Path(tmp) / "tracks.csv", show_progress=False)
        cpu_thread = (time.process_time() - c0) / n
        c0 = time.process_time()
        summ0 = track_video(video, model, Path(tmp) / "tracks0.csv", show_progress=False, decode_thread=False)
        cpu_plain = (time.process_time() - c0) / n
        t0, c0 = time.perf_counter(), time.process_time()
        n2 = sum(1 for _ in VideoReader(video))
        decode = max(decode, n2 / (time.perf_counter() - t0))
        cpu_decode = min(cpu_decode, (time.process_time() - c0) / n2)
        info = VideoReader(video).info
        print(f"video {video.name}: {n} frames {info.width}x{info.height}")
        print(f"training on {len(model.train_poses_)} labels: {t_train:.1f} s")
        print(f"decode only: {decode:.0f} frames/s; decode + track: {summ.fps:.0f} frames/s; "
              f"ratio {summ.fps / decode:.2f} (aim >= 0.5; floor 150 frames/s); lost {summ.n_lost}")
        print(f"without the decode thread: decode + track {summ0.fps:.0f} frames/s; ratio {summ0.fps / decode:.2f}")
        # CPU seconds (time.process_time: all threads of this process) per frame: less sensitive than
        # frames/s to the other jobs of a shared machine
        print(f"CPU per frame: decode only {1e3 * cpu_decode:.3f} ms; decode + track {1e3 * cpu_thread:.3f} ms "
              f"(without the decode thread {1e3 * cpu_plain:.3f} ms); tracking alone about "
              f"{1e3 * (cpu_plain - cpu_decode):.3f} ms")


if __name__ == "__main__":
    main()
