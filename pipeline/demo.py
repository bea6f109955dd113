"""``keyshape demo``: the main job on built-in data, end to end.

It synthesises camcorder footage with ground truth and runs every stage of the
video path that exists on it, printing where each output is.
"""
from __future__ import annotations

import time
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the whole video path on built-in synthetic footage")
    p.add_argument("out_dir", nargs="?", default="keyshape_demo", help="output folder (default: keyshape_demo)")
    p.add_argument("--frames", type=int, default=300, help="frames of synthetic footage (default 300)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def run(args) -> int:
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    outputs: dict[str, Path] = {}
    from data_synth import video as synth

    outputs.update(synth.synthesize(out / "footage", frames=args.frames, seed=args.seed,
                                    preview=out / "footage" / "preview.png"))
    print(f"keyshape demo: done in {time.perf_counter() - t0:.1f} s")
    for name, path in outputs.items():
        print(f"  {name:12s} {path}")
    return 0
