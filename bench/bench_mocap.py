"""Speed of planar bones on the 26,719-vertex ICT-FaceKit head: binding once, then frames per second.

The per-frame cost is reported as a ratio to one plain dense matrix product of the same
output size measured in the same run: ``(n_vertices, 3) = (n_vertices, 28) @ (28, 3)``
(a blend of 28 key shapes, what a blendshape player does per frame), never as a timed
assert.

    PYTHONPATH=. python bench/bench_mocap.py [--bones 100] [--frames 600]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from keyshape.retarget.mocap.planar_bones import PlanarBones  # noqa: E402
from keyshape.retarget.mocap.triangulate import triangulate_markers  # noqa: E402
from keyshape.base.formats.obj import read_obj_vertices  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict-facekit"


def best(fn, repeat=5):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def main(n_bones=100, n_frames=600, seed=0):
    rng = np.random.default_rng(seed)
    v = read_obj_vertices(DATA / "generic_neutral_mesh.obj")
    face = v[:9409]
    # markers: farthest-point samples of the front of the face, enough for ~n_bones triangles
    front = face[face[:, 2] > np.percentile(face[:, 2], 35)]
    pick = [int(rng.integers(len(front)))]
    d = np.linalg.norm(front - front[pick[0]], axis=1)
    n_markers = n_bones // 2 + 12
    for _ in range(n_markers - 1):
        pick.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(front - front[pick[-1]], axis=1))
    markers = front[pick]
    tri = triangulate_markers(markers).triangles
    t_bind = best(lambda: PlanarBones(radius_scale=1.5, unbound="fade").fit(v, markers, tri), 3)
    bones = PlanarBones(radius_scale=1.5, unbound="fade").fit(v, markers, tri)
    frames = markers + rng.normal(0, 0.2, (n_frames,) + markers.shape)
    t_one = best(lambda: [bones.deform(frames[i]) for i in range(50)]) / 50
    t_many = best(lambda: bones.deform_many(frames), 3) / n_frames
    a = rng.normal(size=(len(v), 28))
    b = rng.normal(size=(28, 3))
    t_mat = best(lambda: [a @ b for _ in range(200)]) / 200
    print(f"mesh {len(v)} vertices, {len(markers)} markers, {len(tri)} bones, "
          f"{len(bones.pair_weight_)} vertex-bone pairs ({bones.bound_.sum()} vertices bound)")
    print(f"bind: {t_bind:.2f} s")
    print(f"deform one frame:   {1e3 * t_one:.3f} ms = {1 / t_one:7.0f} frames/s = {t_one / t_mat:5.1f} x one "
          f"({len(v)}x28 @ 28x3) product ({1e3 * t_mat:.3f} ms)")
    print(f"deform_many ({n_frames}): {1e3 * t_many:.3f} ms = {1 / t_many:7.0f} frames/s = "
          f"{t_many / t_mat:5.1f} x the product")
    return t_bind, t_one, t_many, t_mat


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--bones", type=int, default=100)
    ap.add_argument("--frames", type=int, default=600)
    a = ap.parse_args()
    main(a.bones, a.frames)
