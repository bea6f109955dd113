"""``smooth`` against ``nnls``: weight jitter on static stretches and reconstruction error.

For each synthetic ground-truth tracks file given (``keyshape synth video`` truth.csv),
Gaussian tracking noise of ``--noise`` px is added to every point; key shapes are
chosen by spread (k = 12; at most the region's coordinate count, so 4 for
the pupils) on the noisy tracks per region; weights are solved by
``nnls`` and by ``smooth`` (default lambda). Static stretches are the frame pairs
where the region's true shape moves less than ``--still`` px (max over points).

Reported per file and region: RMS frame-to-frame weight change on those pairs
(jitter) and the RMS reconstruction error against the noisy tracks (what the
solver sees), with the smooth/nnls ratios. Without files it uses bench/toy.py.

Run: ``PYTHONPATH=. python bench/smooth_jitter.py truth0.csv truth1.csv ...``
"""
from __future__ import annotations

import argparse

import numpy as np

from keyshape.decompose.regions import available_regions, model_shapes, region_points
from keyshape.decompose.selectors import SpreadSelector
from keyshape.decompose.weights import reconstruct, solve_weights
from keyshape.base.formats.tracks import read_tracks
from keyshape.base.schemes import scheme_for_n_points


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("tracks", nargs="*")
    ap.add_argument("--noise", type=float, default=0.7)
    ap.add_argument("--still", type=float, default=0.1)
    ap.add_argument("-k", type=int, default=12)
    ap.add_argument("--smooth-lambda", type=float, default=0.1)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    if args.tracks:
        items = [(p, read_tracks(p)) for p in args.tracks]
    else:
        from toy import toy_tracks
        items = [(f"toy seed {s}", toy_tracks(600, noise_px=0.0, rng=s)) for s in (5, 6, 7)]
    print("file,region,still_pairs,jitter_nnls,jitter_smooth,jitter_ratio,rms_nnls_px,rms_smooth_px,error_ratio")
    for name, tracks in items:
        scheme = scheme_for_n_points(tracks.n_points)
        truth = model_shapes(tracks)
        noisy = tracks.points + rng.normal(scale=args.noise, size=tracks.points.shape)
        lin = tracks.pose[:, :, :2]
        shapes = np.einsum("tij,tpj->tpi", np.linalg.inv(lin), noisy - tracks.pose[:, None, :, 2])
        for region in available_regions(scheme):
            idx = region_points(scheme, region)
            Q, T = shapes[:, idx], truth[:, idx]
            still = np.abs(np.diff(T, axis=0)).max(axis=(1, 2)) < args.still
            k = min(args.k, Q.shape[1] * 2)   # pupils: 2 points, 4 coordinates -> 4 keys
            sel = SpreadSelector(k).fit(Q)
            out = {}
            for solver in ("nnls", "smooth"):
                w = solve_weights(Q, sel.keys_, sel.neutral_, solver=solver, smooth_lambda=args.smooth_lambda)
                jit = float(np.sqrt((np.diff(w, axis=0)[still] ** 2).sum(1).mean())) if still.any() else np.nan
                d = np.einsum("tij,tpj->tpi", lin, reconstruct(w, sel.keys_, sel.neutral_) - Q)
                out[solver] = jit, float(np.sqrt((d ** 2).sum(-1).mean()))
            (jn, en), (js, es) = out["nnls"], out["smooth"]
            print(f"{name},{region},{int(still.sum())},{jn:.4f},{js:.4f},{js / jn:.3f},{en:.3f},{es:.3f},{es / en:.3f}")


if __name__ == "__main__":
    main()
