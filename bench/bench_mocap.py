"""Speed of planar bones on the 26,719-vertex ICT-FaceKit head: binding once, then time per frame.

Every per-frame cost is printed as a ratio to one plain dense matrix product of the same output
size measured in the same run, ``(n_vertices, 3) = (n_vertices, 28) @ (28, 3)`` float64 (a
blend of 28 key shapes, what a blendshape player does per frame), never as a timed assert.
Both wall-clock and process CPU time (all threads) are printed: on a shared machine the wall
time of every row, the reference included, swings with the other jobs; CPU time swings less.
The reference is measured next to every row, with BLAS's default threads and with one thread,
and the faster is kept (a multi-threaded BLAS on a loaded machine can be several times slower
on this small product, which would flatter the ratios).

Rows: ``deform`` (one frame at a time, what a live tool does) and ``deform_many`` (a whole
take), each in float64 (the default, equal to a pair-by-pair evaluation of eqs. 1, 9-11 to
rounding) and float32 (what ``keyshape mocap`` uses; within 5e-7 of the mesh's extent), then what the
batched float32 frame is made of: the linear part alone (the fixed columns of the one sparse
matrix, all frames of a chunk side by side) and the wedge part of eq. (10) (its factor ``D/d``
is nonlinear in each frame's corner angles: a compiled pass over the wedge pairs, 8 frames at a time).

    PYTHONPATH=. python bench/bench_mocap.py [--bones 100] [--frames 600] [--repeat 5] [--threads 1|0]
        [--compare OLD_planar_bones.py]

``--compare`` times another version of ``planar_bones.py`` (e.g. ``git show
34d62c1:retarget/mocap/planar_bones.py > /tmp/old.py``) in the same run, interleaved, on the
same frames, in both precisions where it has ``dtype``, and prints its largest difference from our
rows of the same precision.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from keyshape.retarget.mocap.planar_bones import PlanarBones  # noqa: E402
from keyshape.retarget.mocap.triangulate import triangulate_markers  # noqa: E402
from keyshape.base.formats.obj import read_obj_vertices  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict-facekit"


def best(fn, repeat=5, per=1):
    """Fastest of ``repeat`` calls: (wall, cpu) seconds per unit (``per`` units a call)."""
    wall, cpu = [], []
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return min(wall) / per, min(cpu) / per


def head_and_markers(n_bones=100, seed=0):
    """The ICT head and ~n_bones/2 + 12 farthest-point markers on the front of its face, triangulated."""
    rng = np.random.default_rng(seed)
    v = read_obj_vertices(DATA / "generic_neutral_mesh.obj")
    face = v[:9409]
    front = face[face[:, 2] > np.percentile(face[:, 2], 35)]
    pick = [int(rng.integers(len(front)))]
    d = np.linalg.norm(front - front[pick[0]], axis=1)
    for _ in range(n_bones // 2 + 11):
        pick.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(front - front[pick[-1]], axis=1))
    markers = front[pick]
    return v, markers, triangulate_markers(markers).triangles, rng


def linear_part(bones, frames, chunk=32):
    """The batched linear part alone: fixed columns for ``chunk`` frames at once, into (frame, vertex)."""
    y, _ = bones._y(frames)
    nfc, nv = bones._fixed_csr.shape[1], bones.n_vertices_
    out = np.empty((len(frames), nv, 3), bones.dtype_)
    for f0 in range(0, len(frames), chunk):
        f1 = min(f0 + chunk, len(frames))
        yb = np.ascontiguousarray(y[f0:f1, :nfc].transpose(1, 0, 2)).reshape(nfc, -1)
        res = (bones._fixed_csr @ yb).reshape(nv, f1 - f0, 3)
        for v0 in range(0, nv, 2048):
            np.add(res[v0:v0 + 2048].transpose(1, 0, 2), bones._still[v0:v0 + 2048], out=out[f0:f1, v0:v0 + 2048])
    return out


def wedge_part(bones, frames):
    """The wedge pairs alone (eq. 10, the compiled pass), 8 frames at a time as ``deform_many`` does."""
    y, g = bones._y(frames)
    out = np.zeros((len(frames), bones.n_vertices_, 3), bones.dtype_)
    for f0 in range(0, len(frames), 8):
        bones._add_wedges(y[f0:f0 + 8], g[f0:f0 + 8], out[f0:f0 + 8])
    return out


def load_module(path):
    """Another version of planar_bones.py, imported from a file (for ``--compare``)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("planar_bones_compare", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(n_bones=100, n_frames=600, repeat=5, threads=True, seed=0, compare=None):
    v, markers, tri, rng = head_and_markers(n_bones, seed)
    t_bind = best(lambda: PlanarBones(radius_scale=1.5, unbound="fade").fit(v, markers, tri), 3)[0]
    bones = {dt: PlanarBones(radius_scale=1.5, unbound="fade", threads=threads, dtype=dt).fit(v, markers, tri)
             for dt in ("float64", "float32")}
    b64 = bones["float64"]
    if compare:     # the other version next to each of ours, in the same precision where it has a dtype
        mod, ours = load_module(compare), bones
        bones = {}
        for dt, bo in ours.items():
            try:
                bones[f"compared file {dt}"] = mod.PlanarBones(radius_scale=1.5, unbound="fade", threads=threads,
                                                               dtype=dt).fit(v, markers, tri)
            except TypeError:       # a version without dtype: float64 only
                if dt == "float64":
                    bones["compared file"] = mod.PlanarBones(radius_scale=1.5, unbound="fade",
                                                             threads=threads).fit(v, markers, tri)
            bones[dt] = bo
    frames = markers + rng.normal(0, 0.2, (n_frames,) + markers.shape)
    a = rng.normal(size=(len(v), 28))
    b = rng.normal(size=(28, 3))
    n_one = min(50, n_frames)
    rows = {}

    def plain():
        # the reference at its best: BLAS with its default threads, or one thread (a small product on
        # a loaded machine is often faster single-threaded); the faster of the two, wall and CPU apart
        t = best(lambda: [a @ b for _ in range(200)], repeat, 200)
        with threadpool_limits(1, "blas"):
            t1 = best(lambda: [a @ b for _ in range(200)], repeat, 200)
        return min(t[0], t1[0]), min(t[1], t1[1])

    # interleave the reference with the rows so that both see the same load
    for dt, bo in bones.items():
        rows[f"deform, {dt}"] = (best(lambda: [bo.deform(frames[i]) for i in range(n_one)], repeat, n_one), plain())
        rows[f"deform_many({n_frames}), {dt}"] = (best(lambda: bo.deform_many(frames), max(2, repeat // 2), n_frames),
                                                 plain())
    b32 = bones["float32"]
    rows["  float32 batched: linear part alone"] = (best(lambda: linear_part(b32, frames), max(2, repeat // 2),
                                                         n_frames), plain())
    rows["  float32 batched: wedge part alone (eq. 10)"] = (best(lambda: wedge_part(b32, frames), max(2, repeat // 2),
                                                                 n_frames), plain())
    err = np.abs(b32.deform_many(frames[:20]) - b64.deform_many(frames[:20])).max()
    if compare:
        for name, bo in bones.items():
            if name.startswith("compared file"):
                ref = bones[name.split()[-1] if name.endswith("32") else "float64"]
                err_old = np.abs(bo.deform_many(frames[:20]) - ref.deform_many(frames[:20])).max()
                print(f"{name}: {compare}; its largest difference from our rows of its precision {err_old:.2g}")
    print(f"mesh {len(v)} vertices, {len(markers)} markers, {len(tri)} bones, "
          f"{len(b64.pair_weight_)} vertex-bone pairs ({b64.bound_.sum()} vertices bound, "
          f"{len(b64._wedge_corner)} of the pairs in wedges); helper thread: {threads}")
    print(f"sparse matrix: {b64._fixed_csc.nnz} fixed entries, {len(b64._wedge_corner)} wedge pairs apart; "
          f"float32 vs float64 max difference {err:.2g} (mesh extent {np.abs(v).max():.1f})")
    print(f"bind: {t_bind:.2f} s")
    print(f"{'per frame':46s} {'wall ms':>8s} {'cpu ms':>8s}   {'x plain (wall)':>14s} {'x plain (cpu)':>13s}")
    for name, ((w, c), (pw, pc)) in rows.items():
        print(f"{name:46s} {1e3 * w:8.3f} {1e3 * c:8.3f}   {w / pw:14.2f} {c / pc:13.2f}"
              f"   (plain {1e3 * pw:.3f} / {1e3 * pc:.3f} ms, {1 / w:6.0f} frames/s)")
    return t_bind, rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--bones", type=int, default=100)
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="1: a helper thread where there is a second core")
    ap.add_argument("--compare", default=None, help="another planar_bones.py to time in the same run")
    args = ap.parse_args()
    main(args.bones, args.frames, args.repeat, bool(args.threads), compare=args.compare)
