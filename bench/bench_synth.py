"""Speed of synthetic footage: ms per frame of rendering and of the whole ``synthesize`` call.

Prints wall-clock and CPU milliseconds per frame and the ratio to a baseline
measured in the same run (encoding the same number of ready-made frames with
``keyshape.base.formats.video.video_writer``), so numbers from loaded machines stay comparable.

    PYTHONPATH=. python bench/bench_synth.py [--frames 300] [--size 640x480] [--face3d [RIG]]

``--face3d`` measures ``keyshape synth face3d`` (the shaded ICT-FaceKit head; RIG defaults to
``../shared/data/ict-facekit``; the one-off load of the rig is outside the per-frame figures).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--face3d", nargs="?", const=str(Path(__file__).resolve().parents[2] / "shared" / "data"
                                                     / "ict-facekit"), default=None, metavar="RIG")
    args = ap.parse_args()
    from keyshape.data_synth.video import SyntheticVideo, parse_size, synthesize
    from keyshape.base.formats.video import video_writer

    size = parse_size(args.size)
    n = args.frames
    with tempfile.TemporaryDirectory() as tmp:
        frame = np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
        w0, c0 = time.perf_counter(), time.process_time()
        with video_writer(Path(tmp) / "base.mp4", 30.0, size) as wr:
            for _ in range(n):
                wr.write(frame)
        base_wall, base_cpu = time.perf_counter() - w0, time.process_time() - c0

        if args.face3d:
            from keyshape.data_synth.face3d import Synthetic3D
            from keyshape.data_synth.face3d import synthesize as synth3d
            sv = Synthetic3D(args.face3d, n, 0, size)
            synthesize = lambda out, **kw: synth3d(out, args.face3d, **kw)  # noqa: E731
        else:
            sv = SyntheticVideo(n, 0, size)
        w0, c0 = time.perf_counter(), time.process_time()
        for t in range(n):
            sv.frame(t)
        render_wall, render_cpu = time.perf_counter() - w0, time.process_time() - c0

        w0, c0 = time.perf_counter(), time.process_time()
        synthesize(Path(tmp) / "out", frames=n, seed=0, size=size)
        all_wall, all_cpu = time.perf_counter() - w0, time.process_time() - c0

    ms = lambda s: 1000.0 * s / n  # noqa: E731
    print(f"frames {n} at {size[0]}x{size[1]}")
    print(f"baseline encode only : {ms(base_wall):6.1f} ms/frame wall, {ms(base_cpu):6.1f} ms/frame cpu")
    print(f"render (no encoding) : {ms(render_wall):6.1f} ms/frame wall, {ms(render_cpu):6.1f} ms/frame cpu"
          f"  ratio to baseline {render_cpu / base_cpu:5.2f}")
    print(f"synthesize (all)     : {ms(all_wall):6.1f} ms/frame wall, {ms(all_cpu):6.1f} ms/frame cpu"
          f"  ratio to baseline {all_cpu / base_cpu:5.2f}  total {all_wall:.1f} s")


if __name__ == "__main__":
    main()
