"""The footage the tracker benchmarks run on: synthetic 640x480 (with its labels and true points)
or a given ``--video`` with ``--labels``. Shared by ``bench_tracker.py`` and ``bench_torch_tracker.py``."""
from __future__ import annotations

import argparse
from pathlib import Path


def add_footage_args(ap: argparse.ArgumentParser, frames: int) -> None:
    """``--frames`` (synthetic length), ``--video``/``--labels`` (real footage instead), ``--scheme``."""
    ap.add_argument("--frames", type=int, default=frames)
    ap.add_argument("--video")
    ap.add_argument("--labels")
    ap.add_argument("--scheme", default="contours48")


def footage(args, tmp) -> tuple[Path, Path, Path | None]:
    """``(video, labels, truth)``: ``args.video``/``args.labels`` (truth None), else synthetic footage of
    ``args.frames`` frames written under ``tmp`` (seed 0; truth: its true tracks)."""
    if args.video:
        return Path(args.video), Path(args.labels), None
    from keyshape.data_synth.video import synthesize

    out = synthesize(Path(tmp) / "footage", frames=args.frames, seed=0)
    return out["video"], out["labels"], out["truth"]
