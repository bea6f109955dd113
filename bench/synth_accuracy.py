"""Tracker accuracy on synthetic footage with exact ground truth (issue 3).

For each seed: ``data_synth.video.synthesize`` (600 frames, 640x480, 12 labels,
default settings), train on the 12 suggested labels, track every frame and
report NME (mean point-to-point error / inter-ocular distance) overall and per
region: mean, 95th percentile, worst frame, lost frames.

    PYTHONPATH=. python bench/synth_accuracy.py [--seeds 0 1 2] [--frames 600]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def nme_table(points, truth, scheme) -> dict:
    """Per-frame NME overall and per region; lost frames (NaN) are counted as failures, not errors."""
    iod = scheme.interocular_distance(truth)
    d = np.linalg.norm(points - truth, axis=-1) / iod[:, None]
    out = {"all": d.mean(1)}
    for name, idx in scheme.regions.items():
        out[name] = d[:, list(idx)].mean(1)
    return out


def run_seed(seed: int, frames: int, workdir: Path) -> dict:
    from keyshape.data_synth.video import synthesize
    from keyshape.tracker.commands import fit_model, track_video
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.schemes import load_scheme

    out = synthesize(workdir / f"s{seed}", frames=frames, seed=seed)
    t0 = time.perf_counter()
    model = fit_model(out["video"], out["labels"], "contours48")
    t_train = time.perf_counter() - t0
    summ = track_video(out["video"], model, workdir / f"s{seed}" / "tracks.csv", show_progress=False)
    tr = read_tracks(workdir / f"s{seed}" / "tracks.csv")
    truth = read_tracks(out["truth"])
    tab = nme_table(tr.points, truth.points, load_scheme("contours48"))
    return {"seed": seed, "train_s": t_train, "fps": summ.fps, "lost": int((~tr.success).sum()), "nme": tab}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=600)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            r = run_seed(seed, args.frames, Path(tmp))
            print(f"seed {seed}: train {r['train_s']:.1f} s, track {r['fps']:.0f} frames/s, lost {r['lost']} frames")
            for name, e in r["nme"].items():
                print(f"  {name:8s} NME mean {np.nanmean(e):.4f}  p95 {np.nanpercentile(e, 95):.4f}  "
                      f"worst {np.nanmax(e):.4f} (frame {int(np.nanargmax(e))})")


if __name__ == "__main__":
    main()
