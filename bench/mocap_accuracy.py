"""Accuracy of the marker path on the synthetic ICT-FaceKit take: dense per-vertex error (mm).

Source actor = the generic ICT face; targets: the same face, then a different face
(identity PCs combined and rescaled; same topology, so the ground truth is the same
expression deltas on that identity). Methods: planar bones with masks (and without), and
IMQ-RBF, TPS, Gaussian-RBF deformers driven by the same retargeted markers.

    PYTHONPATH=. python bench/mocap_accuracy.py [--frames 360] [--seed 0]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mocap_targets import identity_face  # noqa: E402
from keyshape.data_synth.mocap import (FACE_SKIN, discontinuity_regions,  # noqa: E402
                              load_facekit, synthesize)
from keyshape.retarget.mocap.drive import drive_mesh  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict-facekit"


def lip_vertices(kit) -> np.ndarray:
    """Face-skin vertices of the lips: within the mouth landmarks' ellipse (evaluation region)."""
    v = kit.neutral[:FACE_SKIN]
    lm = kit.neutral[kit.landmarks]
    mouth = lm[48:68].mean(axis=0)
    width = np.ptp(lm[48:68, 0])
    height = np.ptp(lm[48:60, 1])
    e = np.linalg.norm((v - mouth)[:, :2] / [0.55 * width, 0.75 * height], axis=1)
    return np.flatnonzero((e < 1.0) & (v[:, 2] > mouth[2] - 1.5))


def errors(pred, truth, idx, frames):
    e = np.linalg.norm(pred[np.ix_(frames, idx)] - truth[np.ix_(frames, idx)], axis=2) * 10.0  # cm -> mm
    return float(e.mean()), float(np.percentile(e, 95))


def run(frames=360, seed=0, data=DATA, out=print):
    kit = load_facekit(data)
    perf = synthesize(kit, frames, rng=seed)
    nface = len(perf.marker_vertices)
    lips = lip_vertices(kit)
    jaw = perf.weights[:, kit.names.index("jawOpen")]
    opening = np.flatnonzero(jaw > 0.25)
    face = np.arange(FACE_SKIN)
    allf = np.arange(frames)
    rows = []
    targets = [("same face", kit.neutral), ("other face", identity_face(kit))]
    for tname, base in targets:
        truth = base[None] + np.einsum("fe,evc->fvc", perf.weights, kit.deltas)
        tm = {lab: base[v] for lab, v in zip(perf.labels[:nface], perf.marker_vertices)}
        regions = discontinuity_regions(kit, perf.labels[:nface])
        for method, reg in (("planar+masks", regions), ("planar", None), ("imq", None), ("tps", None),
                            ("gaussian", None)):
            t0 = time.perf_counter()
            res = drive_mesh(perf.markers_mm, perf.labels, base, tm, method=method.split("+")[0],
                             rigid_names=[s for s in perf.labels if s.startswith("jig")], regions=reg)
            dt = time.perf_counter() - t0
            fm, fp = errors(res.vertices, truth, face, allf)
            lm_, lp = errors(res.vertices, truth, lips, opening)
            rows.append((tname, method, fm, fp, lm_, lp, dt))
            out(f"{tname:10s} {method:13s} face mean {fm:6.3f} p95 {fp:6.3f} | lips(open) mean {lm_:6.3f} "
                f"p95 {lp:6.3f} mm | {dt:5.1f} s")
    return rows, len(opening), len(lips)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=360)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rows, n_open, n_lips = run(a.frames, a.seed)
    print(f"\n{n_open} mouth-open frames (jawOpen > 0.25), {n_lips} lip vertices, face = vertices 0-9408")
    print("| target | method | face mean | face p95 | lips mean | lips p95 |\n|---|---|---|---|---|---|")
    for t, m, fm, fp, lm_, lp, _ in rows:
        print(f"| {t} | {m} | {fm:.2f} | {fp:.2f} | {lm_:.2f} | {lp:.2f} |")
