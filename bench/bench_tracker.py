"""Tracking speed against plain decoding of the same video, measured in the same run (issue 3).

Synthesises 640x480 footage (or takes ``--video`` with ``--labels``), trains on
its labels (timed) and reports frames/s of decode-only, of decode + tracking
(decoding in a background thread, the default) and their ratio, and the same
without the decode thread. Prints ratios, never asserts times.

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
        t0 = time.perf_counter()
        n = sum(1 for _ in VideoReader(video))
        decode = n / (time.perf_counter() - t0)
        summ = track_video(video, model, Path(tmp) / "tracks.csv", show_progress=False)
        summ0 = track_video(video, model, Path(tmp) / "tracks0.csv", show_progress=False, decode_thread=False)
        t0 = time.perf_counter()
        n2 = sum(1 for _ in VideoReader(video))
        decode = max(decode, n2 / (time.perf_counter() - t0))
        info = VideoReader(video).info
        print(f"video {video.name}: {n} frames {info.width}x{info.height}")
        print(f"training on {len(model.train_poses_)} labels: {t_train:.1f} s")
        print(f"decode only: {decode:.0f} frames/s; decode + track: {summ.fps:.0f} frames/s; "
              f"ratio {summ.fps / decode:.2f} (aim >= 0.5; floor 150 frames/s); lost {summ.n_lost}")
        print(f"without the decode thread: decode + track {summ0.fps:.0f} frames/s; ratio {summ0.fps / decode:.2f}")


if __name__ == "__main__":
    main()
