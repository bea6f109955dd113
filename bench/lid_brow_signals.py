"""Issue 23: are the track's lids and brows shrunk, or is the reference noisy? Three landmarkers compared.

Per frame, four signals from each of the track (contours48 or ibug68), dlib's 68 points and MediaPipe's
478 (``../shared/data/video/references/CLIP_references.npz``), in inter-ocular units in the eye line's
frame: outer-brow height, inner-brow height (above the eye centres), each eye's lid gap. When the three
measure one signal ``s`` with gains ``g`` and independent errors, ``cov(X, Y) = g_X g_Y var(s)``, so (``bench/three_hat.py``)

- ``gT/gD = cov(T, M) / cov(D, M)``: the track's gain relative to dlib's, free of the attenuation that
  dlib's own error puts on a least-squares slope of T on D (what ``rig_fidelity.py`` reports as gain);
- ``rho_X = sqrt(cov(X, Y) cov(X, Z) / cov(Y, Z)) / sd(X)``: the correlation of X with the common
  signal. Against a reference R, no X can reach r above ``rho_R`` (errors independent).

Also printed: the plain r and least-squares slope of T on D (the judge's view), r with MediaPipe of
the track and of dlib, and jitter (sd of second differences over sd of the signal). Training frames
(``LABELS/*.pts``) are left out.

    python bench/lid_brow_signals.py CLIP TRACKS.csv LABELS_DIR
"""
from __future__ import annotations

import argparse
import glob
import os
from pathlib import Path

import numpy as np

from keyshape.base.formats.tracks import read_tracks
from three_hat import common_signal

REFS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video" / "references"
# per scheme (point count): eye corners (outer, inner of the image-left eye, inner, outer of the
# other), outer brow ends, inner brow ends, lid pairs of each eye
INDEX = {
    48: dict(corners=(10, 14, 18, 22), outer=(0, 9), inner=(4, 5), lid_l=((12, 16),), lid_r=((20, 24),)),
    68: dict(corners=(36, 39, 42, 45), outer=(17, 26), inner=(21, 22), lid_l=((37, 41), (38, 40)),
             lid_r=((43, 47), (44, 46))),
    478: dict(corners=(33, 133, 362, 263), outer=(46, 276), inner=(55, 285), lid_l=((159, 145),),
              lid_r=((386, 374),)),
}


def signals(points: np.ndarray) -> dict[str, np.ndarray]:
    """(n_frames, n_points, 2) -> outer/inner brow height and each lid gap per frame (inter-ocular units)."""
    ix = INDEX[points.shape[1]]
    p = points
    a, b, c, d = ix["corners"]
    e0, e1 = (p[:, a] + p[:, b]) / 2, (p[:, c] + p[:, d]) / 2
    iod = np.linalg.norm(p[:, a] - p[:, d], axis=-1)
    u = (e1 - e0) / np.linalg.norm(e1 - e0, axis=-1, keepdims=True)
    up = np.stack([u[:, 1], -u[:, 0]], -1)                          # image y points down
    mid = (e0 + e1) / 2

    def height(idx):
        return np.mean([np.einsum("td,td->t", p[:, i] - mid, up) for i in idx], 0) / iod

    def gap(pairs):
        return np.mean([np.linalg.norm(p[:, i] - p[:, j], axis=-1) for i, j in pairs], 0) / iod

    return {"brow outer": height(ix["outer"]), "brow inner": height(ix["inner"]),
            "lid gap L": gap(ix["lid_l"]), "lid gap R": gap(ix["lid_r"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clip")
    ap.add_argument("tracks")
    ap.add_argument("labels")
    a = ap.parse_args()
    ref = np.load(REFS / f"{a.clip}_references.npz")
    tr = read_tracks(a.tracks)
    fr = np.asarray(tr.frame)
    lab = [int(os.path.basename(p)[:6]) for p in glob.glob(os.path.join(a.labels, "*.pts"))]
    D, M = ref["dlib68"][fr].astype(float), ref["mediapipe478"][fr].astype(float)
    ok = (np.asarray(tr.success, bool) & np.isfinite(D).all((1, 2)) & np.isfinite(M).all((1, 2))
          & ~np.isin(fr, lab))
    st, sd, sm = (signals(x[ok]) for x in (np.asarray(tr.points), D, M))
    print(f"{a.clip}: {int(ok.sum())} frames")
    print(f"{'signal':11s} | {'r T,D':>5s} {'slope':>5s} | {'gT/gD':>5s} | {'rho T':>5s} {'rho D':>5s} {'rho M':>5s} | "
          f"{'r T,M':>5s} {'r D,M':>5s} | jitter T / D / M")
    for k in st:
        x = np.stack([st[k], sd[k], sm[k]])
        hat = common_signal(x)
        rho = hat["rho"]
        jit = [np.std(np.diff(v, 2)) / np.std(v) for v in x]
        r = np.corrcoef(x)
        print(f"{k:11s} | {r[0, 1]:5.3f} {np.polyfit(x[1], x[0], 1)[0]:5.3f} | {hat['gain'][0, 1]:5.3f} | "
              f"{rho[0]:5.3f} {rho[1]:5.3f} {rho[2]:5.3f} | {r[0, 2]:5.3f} {r[1, 2]:5.3f} | "
              f"{jit[0]:.2f} / {jit[1]:.2f} / {jit[2]:.2f}")


if __name__ == "__main__":
    main()
