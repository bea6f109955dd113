"""Timing of the weight solvers on 100,000 frames x 48 points x 24 keys, as ratios to a baseline.

Baseline, measured in the same run: the unconstrained least-squares solve of the
same size (``np.linalg.lstsq`` of all frames at once, the paper's "bad example").
Data: the toy low-rank performance (bench/toy.py) tiled to 100,000 frames with
fresh tracking noise, all 48 points, 24 key frames chosen by spread.

Run: ``python bench/bench_decompose.py [--frames N] [--admm] [--plain-admm]``. Wall-clock ratios, and
process CPU-time ratios beside them (steadier on a shared machine; they add up all threads).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from keyshape.decompose.regions import model_shapes
from keyshape.decompose.selectors import SpreadSelector
from toy import toy_tracks
from keyshape.decompose.weights import lstsq_weights, nnls_result, smooth_result


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--keys", type=int, default=24)
    ap.add_argument("--admm", action="store_true",
                    help="also time the smooth solver's former default (Anderson-accelerated ADMM)")
    ap.add_argument("--plain-admm", action="store_true",
                    help="also time ADMM without Anderson acceleration (the default before that)")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    base = model_shapes(toy_tracks(2000, noise_px=0.0, rng=0))
    reps = -(-args.frames // len(base))
    shapes = np.tile(base, (reps, 1, 1))[:args.frames] + rng.normal(scale=0.5, size=(args.frames, 48, 2))
    sel = SpreadSelector(args.keys).fit(shapes[:5000])
    keys, neutral = sel.keys_, sel.neutral_
    print(f"{args.frames} frames x {shapes.shape[1]} points x {args.keys} keys")

    def timed(name, fn):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        return name, (time.perf_counter() - t, time.process_time() - c), out

    res = [timed("lstsq (baseline)", lambda: lstsq_weights(shapes, keys, neutral)),
           timed("nnls", lambda: nnls_result(shapes, keys, neutral)),
           timed("smooth (lambda 0.1)", lambda: smooth_result(shapes, keys, neutral, 0.1))]
    if args.admm:
        res.append(timed("smooth, ADMM", lambda: smooth_result(shapes, keys, neutral, 0.1,
                                                                method="admm")))
    if args.plain_admm:
        res.append(timed("smooth, plain ADMM", lambda: smooth_result(shapes, keys, neutral, 0.1,
                                                                      method="admm", anderson=0)))
    base_t, base_c = res[0][1]
    for name, (dt, dc), out in res:
        extra = ""
        if name == "nnls":
            extra = f"  all converged: {bool(out.converged.all())}, min weight {out.weights.min():.3g}"
        if name.startswith("smooth"):
            extra = f"  {out.method} iterations: {out.iterations}, converged: {bool(out.converged.all())}"
            if name != "smooth (lambda 0.1)":
                extra += f", max |w - active-set w| {np.abs(out.weights - res[2][2].weights).max():.2g}"
        print(f"{name:22s} {dt:8.2f} s   ratio to lstsq {dt / base_t:6.2f}   (CPU time {dc:7.2f} s, ratio "
              f"{dc / base_c:6.2f}){extra}")


if __name__ == "__main__":
    main()
