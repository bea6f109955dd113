"""Speed of retargeting: all frames of a dense mesh as one matrix product.

10,000 frames x 26,719 vertices (the ICT-FaceKit head) x 24 targets, float32
output (10,000 x 80,157 x 4 B = 3.2 GB; float64 would be 6.4 GB), evaluated by
:class:`retarget.targets.blend.BlendBasis` and compared, in the same run, with a plain
numpy matmul of the same size into the same preallocated buffer (the floor any
implementation can reach). One output buffer is reused by every variant so the
run peaks at about 3.3 GB. Also reported: the delta form (the neutral is one more
basis row driven by a constant weight, so still one product)
and a streaming variant that evaluates 1,000-frame chunks into a 320 MB buffer
(what an exporter writing frames as it goes needs).

Usage: python bench/bench_retarget.py [--frames 10000] [--vertices 26719] [--targets 24] [--repeat 3]
Prints times and ratios; no asserts (timings are machine-dependent).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from keyshape.retarget.targets.blend import BlendBasis


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--vertices", type=int, default=26_719)
    ap.add_argument("--targets", type=int, default=24)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--chunk", type=int, default=1000)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    n, v, k = a.frames, a.vertices, a.targets
    targets = rng.normal(size=(k, v, 3))
    neutral = rng.normal(size=(v, 3))
    w = rng.uniform(0, 1, size=(n, k))
    print(f"{n} frames x {v} vertices x {k} targets, float32 output {n * v * 3 * 4 / 1e9:.2f} GB")
    out = np.zeros((n, v, 3), np.float32)
    out[...] = 1.0                     # touch every page before timing anything
    flat = out.reshape(n, -1)
    w32 = w.astype(np.float32)
    b32 = np.ascontiguousarray(targets.reshape(k, -1), dtype=np.float32)
    ab = BlendBasis("absolute", np.float32).fit(targets)
    db = BlendBasis("delta", np.float32).fit(targets, neutral)
    buf = np.empty((a.chunk, v, 3), np.float32)

    def stream():
        for s in range(0, n, a.chunk):
            ab.transform(w[s:s + a.chunk], out=buf[: len(w[s:s + a.chunk])])
    variants = {"numpy": lambda: np.matmul(w32, b32, out=flat), "absolute": lambda: ab.transform(w, out=out),
                "delta": lambda: db.transform(w, out=out), "stream": stream}
    times = {name: [] for name in variants}
    for _ in range(a.repeat):          # interleaved, so machine load hits every variant alike
        for name, fn in variants.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    ab.transform(w[:5], out=out[:5])
    np.testing.assert_allclose(flat[:5], w32[:5] @ b32, rtol=1e-5, atol=1e-4)
    t_np, t_abs, t_delta, t_stream = (min(times[k]) for k in variants)
    print(f"plain numpy matmul (baseline)   {t_np:7.3f} s   {n / t_np:9.0f} frames/s")
    for name, t in (("BlendBasis absolute", t_abs), ("BlendBasis delta (neutral row)", t_delta),
                    (f"absolute, {a.chunk}-frame chunks", t_stream)):
        print(f"{name:31s} {t:7.3f} s   {n / t:9.0f} frames/s   ratio to baseline {t / t_np:.2f}x")


if __name__ == "__main__":
    main()
