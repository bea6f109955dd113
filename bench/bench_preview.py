"""Speed of the rig preview (issue 26: >= 25 frames/s in the render loop at 480 px on the ICT-FaceKit
head; the 240-frame preview through ``keyshape preview`` in <= 12 s, loading included).

Prints, each with the load average and a baseline measured in the same run:

- the render loop: frames/s (wall, on the preview's threads) and CPU ms per frame of
  :class:`keyshape.retarget.output.preview.RigRenderer` as ``keyshape preview`` fits it (``cull_hidden``: only the
  triangles some frame shows), against the same renderer drawing every front-facing triangle, with the
  share of pixels that differ between the two (more than 30 of 255 levels);
- with ``--video --tracks --curves``: the whole command's wall time (``keyshape preview VIDEO --tracks T
  --curves C --rig RIG --frames 0:N -o OUT.mp4``) against decoding the same frames, and against the same
  command run by another checkout's environment (``--baseline-python /path/to/venv/bin/python``: old / new).

    python bench/bench_preview.py [--rig ../shared/data/ict-facekit] [--size 480] [--frames 240]
        [--video franck.mp4 --tracks tracks.csv --curves curves.csv] [--baseline-python /work/venv/bin/python]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def load() -> str:
    return "load average " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def render_loop(rig, curves, head, size: int, cull: bool, landmarks) -> tuple[list, float, float, float]:
    """(frames, fit seconds, wall seconds, CPU seconds) of rendering every row of ``curves``."""
    from keyshape.retarget.output.preview import RigRenderer, ordered_map
    t = time.perf_counter()
    r = RigRenderer(rig, (size, size), landmarks=landmarks, cull_hidden=cull).fit(curves, head)
    fit = time.perf_counter() - t
    r.render_curves(curves[0], None if head is None else head[0])          # warm up
    t, c = time.perf_counter(), time.process_time()
    jobs = ((None, (curves[i], None if head is None else head[i])) for i in range(len(curves)))
    out = [img for _, img, _ in ordered_map(lambda x: r.render_curves(*x), jobs)]
    return out, fit, time.perf_counter() - t, time.process_time() - c


def command(python: str, a, out: Path) -> float:
    """Wall seconds of ``keyshape preview`` run by the interpreter ``python`` (its environment's keyshape)."""
    cmd = [python, "-m", "keyshape", "preview", a.video, "--tracks", a.tracks, "--curves", a.curves,
           "--rig", a.rig, "--frames", f"0:{a.frames}", "-o", str(out)]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default=str(REPO.parent / "shared" / "data" / "ict-facekit"))
    ap.add_argument("--size", type=int, default=480)
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--video", default=None)
    ap.add_argument("--tracks", default=None)
    ap.add_argument("--curves", default=None, help="rig curves CSV (default: random sparse curves, no head turn)")
    ap.add_argument("--baseline-python", default=None,
                    help="the python of another checkout's environment: the command run with its code too")
    a = ap.parse_args()
    from keyshape.retarget.rig.model import default_landmarks, load_rig, rig_landmarks
    t = time.perf_counter()
    rig = load_rig(a.rig)
    t_load = time.perf_counter() - t
    head = None
    if a.curves:
        from keyshape.retarget.output.preview_cli import _curves_on_rig
        _, curves, head = _curves_on_rig(a.curves, rig)
        curves, head = curves[: a.frames], None if head is None else head[: a.frames]
    else:
        rng = np.random.default_rng(0)
        n, k = a.frames, rig.n_shapes
        curves = rng.uniform(0, 0.6, (n, k)) * (rng.uniform(size=(n, k)) < 0.15)
    lm = None
    if default_landmarks(rig.n_vertices, "contours48"):      # the contours drawn over the rig, as a preview does
        from keyshape.base.schemes import load_scheme
        lm = (rig_landmarks(rig, "contours48")[0], load_scheme("contours48"))
    print(f"{rig.n_vertices} vertices, {len(rig.mesh.triangles)} triangles, {a.size}x{a.size}, "
          f"{len(curves)} frames; rig loaded in {t_load:.2f} s; {load()}")
    new, fit_new, wall_new, cpu_new = render_loop(rig, curves, head, a.size, True, lm)
    old, fit_old, wall_old, cpu_old = render_loop(rig, curves, head, a.size, False, lm)
    diff = np.array([(np.abs(x.astype(int) - y.astype(int)).max(axis=2) > 30).mean() for x, y in zip(new, old)])
    n = len(curves)
    print(f"render loop, visible triangles only: {n / wall_new:5.1f} frames/s "
          f"({1000 * cpu_new / n:5.1f} CPU ms/frame, fit {fit_new:.2f} s)")
    print(f"render loop, every front triangle:   {n / wall_old:5.1f} frames/s "
          f"({1000 * cpu_old / n:5.1f} CPU ms/frame, fit {fit_old:.2f} s)")
    print(f"  speed-up {wall_old / wall_new:.2f}x; pixels differing by more than 30 levels: mean "
          f"{100 * diff.mean():.3f}%, worst frame {100 * diff.max():.3f}%; {load()}")
    if a.video and a.tracks and a.curves:
        from keyshape.base.formats.video import VideoReader
        t = time.perf_counter()
        for i, _ in VideoReader(a.video):
            if i >= a.frames - 1:
                break
        t_dec = time.perf_counter() - t
        with tempfile.TemporaryDirectory() as tmp:
            t_new = command(sys.executable, a, Path(tmp) / "new.mp4")
            print(f"keyshape preview, {a.frames} frames, whole command: {t_new:.1f} s "
                  f"({a.frames / t_new:.1f} frames/s); decoding those frames {t_dec:.2f} s; {load()}")
            if a.baseline_python:
                t_old = command(a.baseline_python, a, Path(tmp) / "old.mp4")
                print(f"  run by {a.baseline_python} (another checkout): {t_old:.1f} s; "
                      f"old / new = {t_old / t_new:.2f}x; {load()}")


if __name__ == "__main__":
    main()
