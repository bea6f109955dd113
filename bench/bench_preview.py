"""Speed of the rig preview renderer on the full ICT-FaceKit head (issue 14: >= 10 frames/s).

Prints CPU seconds per frame of :class:`keyshape.retarget.preview.RigRenderer` (painter's algorithm
on OpenCV fillPoly) at several depth-band sizes, the share of pixels that differ from the thinnest
bands (the exactness cost), and the ratio to the project's z-buffer renderer
(:func:`keyshape.retarget.render.render`) measured in the same run.

    python bench/bench_preview.py [--rig ../shared/data/ict-facekit] [--size 288] [--frames 10]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default=str(REPO.parent / "shared" / "data" / "ict-facekit"))
    ap.add_argument("--size", type=int, default=288)
    ap.add_argument("--frames", type=int, default=10)
    a = ap.parse_args()
    from keyshape.retarget.preview import RigRenderer
    from keyshape.retarget.render import render
    from keyshape.retarget.rig import load_rig
    rig = load_rig(a.rig)
    rng = np.random.default_rng(0)
    curves = rng.uniform(0, 0.6, (a.frames, rig.n_shapes)) * (rng.uniform(size=(a.frames, rig.n_shapes)) < 0.15)
    V = rig.evaluate(curves)
    out = {}
    for band in (100, 2000, 6000):
        r = RigRenderer(rig, (a.size, a.size), band=band).fit(curves)
        r.render(V[0])
        t = time.process_time()
        out[band] = [r.render(v) for v in V]
        out[band + 0.5] = (time.process_time() - t) / len(V)
    t = time.process_time()
    for v in V[:3]:
        render(v, rig.mesh.triangles, r.camera_)
    z = (time.process_time() - t) / 3
    print(f"{rig.n_vertices} vertices, {len(rig.mesh.triangles)} triangles, {a.size}x{a.size}, {a.frames} frames")
    for band in (100, 2000, 6000):
        diff = np.mean([(np.abs(x.astype(int) - y.astype(int)).sum(2) > 30).mean()
                        for x, y in zip(out[band], out[100])])
        s = out[band + 0.5]
        print(f"band {band:5d}: {s * 1000:6.1f} CPU ms/frame = {1 / s:5.1f} frames per CPU second; "
              f"{100 * diff:.2f}% pixels differ from band 100; z-buffer render / this = {z / s:.1f}x")


if __name__ == "__main__":
    main()
