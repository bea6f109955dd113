"""Check that a tracker speed refactor keeps the tracked points (issue 16).

Tracks a synthetic 640x480 clip (seed 0) with the default tracker and a few
option variants and saves or compares everything a frame yields: points,
poses, residuals, success. Run it with the code before the change (``--save``)
and after (``--compare``); prints the largest differences.

    PYTHONPATH=. python bench/check_tracker_points.py --save before.npz [--frames 300]
    PYTHONPATH=. python bench/check_tracker_points.py --compare before.npz
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

VARIANTS = {"default": {}, "region_iter0": {"region_iter": 0}, "no_blend": {"global_weight": 0.0},
            "iter3": {"region_iter": 3}}


def run(frames: int) -> dict[str, np.ndarray]:
    from keyshape.base.formats.video import VideoReader
    from keyshape.data_synth.video import synthesize
    from keyshape.tracker.commands import fit_model
    from keyshape.tracker.commands import track_frames
    from keyshape.tracker.fitting import Tracker

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        syn = synthesize(Path(tmp) / "footage", frames=frames, seed=0)
        model = fit_model(syn["video"], syn["labels"], "contours48")
        imgs = [f for _, f in VideoReader(syn["video"])]
        # the command's path (decode thread, iter_track's settings), default tracker
        t0, c0 = time.perf_counter(), time.process_time()
        tracks = track_frames(syn["video"], model)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        print(f"track_frames: {len(imgs) / dt:.0f} frames/s decode + track, {1e3 * dc / len(imgs):.3f} ms CPU/frame")
        out["track_frames_points"] = tracks.points
        out["track_frames_pose"] = tracks.pose
        out["track_frames_residual"] = tracks.confidence
        out["track_frames_success"] = tracks.success
        out["track_frames_iterations"] = np.zeros(len(tracks.points), int)
    for name, opts in VARIANTS.items():
        tr = Tracker(model, **opts)
        t0, c0 = time.perf_counter(), time.process_time()
        res = [tr.step(f, i) for i, f in enumerate(imgs)]
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        print(f"{name}: {len(imgs) / dt:.0f} frames/s track only, {1e3 * dc / len(imgs):.3f} ms CPU/frame")
        out[f"{name}_points"] = np.stack([r.points for r in res])
        out[f"{name}_pose"] = np.stack([r.pose for r in res])
        out[f"{name}_residual"] = np.array([r.residual for r in res])
        out[f"{name}_success"] = np.array([r.success for r in res])
        out[f"{name}_iterations"] = np.array([r.iterations for r in res])
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--save")
    g.add_argument("--compare")
    args = ap.parse_args()
    got = run(args.frames)
    if args.save:
        np.savez(args.save, **got)
        return
    ref = np.load(args.compare)
    worst = 0.0
    for name in ["track_frames", *VARIANTS]:
        p, q = got[f"{name}_points"], ref[f"{name}_points"]
        same_nan = bool((np.isnan(p) == np.isnan(q)).all())
        d = float(np.nanmax(np.abs(p - q))) if np.isfinite(p - q).any() else 0.0
        worst = max(worst, d)
        print(f"{name}: max |points - before| {d:.2e} px; NaN pattern equal {same_nan}; "
              f"max |pose| diff {np.nanmax(np.abs(got[f'{name}_pose'] - ref[f'{name}_pose'])):.2e}; "
              f"max |residual (track_frames: confidence)| diff {np.nanmax(np.abs(got[f'{name}_residual'] - ref[f'{name}_residual'])):.2e}; "
              f"success equal {bool((got[f'{name}_success'] == ref[f'{name}_success']).all())}; "
              f"iterations equal {bool((got[f'{name}_iterations'] == ref[f'{name}_iterations']).all())}")
    print(f"largest point difference over all variants: {worst:.2e} px ({'OK' if worst <= 1e-3 else 'ABOVE'} 1e-3)")


if __name__ == "__main__":
    main()
