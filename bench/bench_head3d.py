"""Speed of the 3D head pose (issue 26): :class:`~keyshape.decompose.head3d.HeadPose3D` on real tracks.

Times, for this checkout's ``head3d`` and for a baseline copy of the module (``--old``, e.g.
``git show main:decompose/head3d.py > /tmp/head3d_old.py``) in the same run:

* **fit**: ``fit`` on the take's first ``--frames`` frames (the batched solve over all frames, twice
  on the rest frame before it);
* **batch**: ``camera_pose`` on those frames at once (what ``keyshape decompose`` / ``retarget`` run);
* **one frame**: ``camera_pose`` called on each of ``--single`` frames alone (what ``keyshape live`` runs);

and prints ms per frame, the ratios old / new, the largest differences of the poses (radians, cm) and
the 1-minute load average (the machine may be shared).

    python bench/bench_head3d.py --tracks TRACKS.csv --old /tmp/head3d_old.py [--frames 2000] [--single 200]
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import time

import numpy as np


def _module(path: str):
    spec = importlib.util.spec_from_file_location("head3d_old", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _best(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run(mod, pts: np.ndarray, single: int, repeat: int, scheme) -> tuple[dict, tuple]:
    from keyshape.base.schemes import load_head_template
    X, w = load_head_template(scheme)
    est = mod.HeadPose3D(X, w, scheme.rigid)
    times = {"fit": _best(lambda: est.fit(pts), repeat) / len(pts) * 1e3}
    times["batch"] = _best(lambda: est.camera_pose(pts), repeat) / len(pts) * 1e3
    one = pts[:single]
    times["one frame"] = _best(lambda: [est.camera_pose(one[i:i + 1]) for i in range(len(one))], repeat) \
        / len(one) * 1e3
    R, t = est.camera_pose(pts)
    R1 = np.concatenate([est.camera_pose(one[i:i + 1])[0] for i in range(len(one))])
    return times, (R, t, R1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tracks", required=True)
    ap.add_argument("--old", required=True, help="a baseline copy of decompose/head3d.py")
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--single", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose import head3d
    from keyshape.decompose.regions import image_points
    tracks = read_tracks(args.tracks)
    pts = image_points(tracks, args.tracks)[:args.frames]
    scheme = scheme_for_n_points(tracks.n_points)
    old, (Ro, to, R1o) = run(_module(args.old), pts, args.single, args.repeat, scheme)
    new, (Rn, tn, R1n) = run(head3d, pts, args.single, args.repeat, scheme)
    load = os.getloadavg()[0]
    print(f"{len(pts)} frames ({int(np.isfinite(pts).all(axis=(1, 2)).sum())} tracked), {args.single} one-frame calls; "
          f"load {load:.1f}")
    for k in old:
        print(f"{k:10s} old {old[k]:7.3f} ms/frame  new {new[k]:7.3f} ms/frame  old/new {old[k] / new[k]:5.1f}x")
    ok = np.isfinite(Ro).all(axis=(1, 2))
    print(f"batch: largest difference {np.abs(Rn[ok] - Ro[ok]).max():.2e} (rotation entries), "
          f"{np.abs(tn[ok] - to[ok]).max():.2e} cm; one frame: {np.nanmax(np.abs(R1n - R1o)):.2e}; "
          f"NaN frames alike: {bool((np.isnan(Rn) == np.isnan(Ro)).all())}")


if __name__ == "__main__":
    main()
