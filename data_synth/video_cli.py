"""``keyshape synth video``: synthetic camcorder footage of a talking face with exact ground truth."""
from __future__ import annotations

import time

from keyshape.base import options


def register(subparsers) -> None:
    """Add ``video`` under ``keyshape synth``."""
    p = subparsers.add_parser(
        "video", help="synthetic talking-face footage with ground-truth contours48 landmarks",
        description="Write video.mp4, truth.csv (contours48 landmarks and head pose per frame), "
                    "labels/ (suggested training frames as .pts) and truth.json (hidden expression "
                    "weights and basis) into OUT_DIR.")
    p.add_argument("out_dir", metavar="OUT_DIR", help="output folder (created)")
    add_footage_options(p, frames=600)
    p.set_defaults(func=run)


def add_footage_options(p, frames: int) -> None:
    """The options every synthetic footage command shares (``synth video``, ``synth face3d``)."""
    p.add_argument("--frames", type=options.synth_frames, default=frames, help=f"number of frames (default {frames})")
    p.add_argument("--seed", type=int, default=0, help="random seed: same seed, same footage (default 0)")
    p.add_argument("--size", default="640x480", help="frame size WIDTHxHEIGHT (default 640x480)")
    p.add_argument("--fps", type=options.fps, default=30.0, help="frame rate (default 30)")
    p.add_argument("--labels", type=int, default=12, help="suggested training frames written to labels/ (default 12)")
    p.add_argument("--preview", metavar="PNG", default=None,
                   help="also write a contact sheet of 12 frames with the ground truth drawn")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder keyshape did not make (only its own files are replaced)")


def run(args) -> int:
    from keyshape.data_synth.video import synthesize

    return run_footage(args, "video", lambda tmp, size, preview: synthesize(
        tmp, frames=args.frames, seed=args.seed, size=size, fps=args.fps, labels=args.labels, preview=preview,
        verbose=True))


def run_footage(args, kind: str, make, check=None) -> int:
    """What every ``keyshape synth`` footage command does around its generator: check the shared options
    (and ``check()``) before any work, run ``make(tmp, size, preview)`` into a hidden folder of OUT_DIR
    (a ``--preview`` inside OUT_DIR goes there too), move its files in, print where they are."""
    from pathlib import Path

    from keyshape.base.files import atomic_dir, check_output, check_output_dir
    from keyshape.data_synth.video import _check_args, parse_size

    size = parse_size(args.size)
    _check_args(args.frames, args.seed, size, args.fps, args.labels)
    if check is not None:
        check()
    out_dir = Path(args.out_dir)
    check_output_dir(out_dir)
    if args.preview:
        if Path(args.preview).suffix.lower() != ".png":
            from keyshape.base.errors import InputError
            raise InputError("--preview: the contact sheet must be a .png file", args.preview)
        check_output(args.preview)
    t0 = time.perf_counter()
    with atomic_dir(out_dir, kind=f"synth {kind}") as tmp:
        preview = args.preview
        if preview and Path(preview).resolve().parent == out_dir.resolve():
            preview = tmp / Path(args.preview).name
        out = make(tmp, size, preview)
    out = {k: (out_dir / Path(v).relative_to(tmp) if Path(v).is_relative_to(tmp) else Path(v))
           for k, v in out.items()}
    dt = time.perf_counter() - t0
    print(f"keyshape synth {kind}: {args.frames} frames in {dt:.1f} s ({1000 * dt / args.frames:.1f} ms/frame)")
    for name, path in out.items():
        print(f"  {name:11s} {path}")
    return 0
