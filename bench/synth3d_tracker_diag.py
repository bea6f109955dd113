"""Why the person-specific tracker errs on the 3D synthetic take: per region, per head pose, and
what an oracle pose and a depth-aware model frame would leave (issue 23).

On a work folder of ``bench/synth3d_accuracy.py`` (``take/`` with ``video.mp4``, ``truth.csv``,
``head.csv``, ``labels/``) it trains the default model on the take's labels, tracks the take in
memory and prints, against the truth landmarks (inter-ocular units):

1. the error per region (brows, eye contours, pupils, lips) by |head yaw| and by head pitch, and the
   labelled frames' yaw and pitch (do the labels cover the head's range?);
2. the error by distance in time from the nearest labelled frame, and its slow (9-frame mean) and
   fast parts (bias or jitter?);
3. the oracle readings: the model read at the truth's own pose (the least-squares affine of the
   truth onto the model's reference, regions read in place, no refinement), so that the pose
   search's share of the error and the reading's can be told apart; and the same with a
   **depth-aware model frame**: image point ``= M [X, Y, Z(X, Y)] + t`` (M 2x3: a weak-perspective
   camera on a generic face's depth ``Z`` over the model frame, from ``head3d.json`` and its nose, a
   thin-plate spline) instead of the 2D affine, its labels and training patches sampled through it,
   the pose fitted to the truth's points weighted as a head pose fit weights them (the rigid ones);
4. with ``--more-labels``: the same tracker trained on 24 and 48 labelled frames (the 12 plus frames
   spread over the take), how much of the error more labels would remove.

    PYTHONPATH=. python bench/synth3d_tracker_diag.py WORK [--more-labels]
"""
from __future__ import annotations

import argparse
from pathlib import Path
from unittest import mock

import cv2
import numpy as np

GROUPS = {"brows": list(range(0, 10)), "eyes": list(range(10, 26)), "pupils": [26, 27], "lips": list(range(28, 48))}


def load(work: Path):
    from keyshape.base.formats.labels import read_labels
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.video import VideoReader
    truth = read_tracks(work / "take" / "truth.csv").points
    frames = VideoReader(work / "take" / "video.mp4", gray=True).read_frames(np.arange(len(truth)))
    head = np.genfromtxt(work / "take" / "head.csv", delimiter=",", names=True)
    labs, _ = read_labels(work / "take" / "labels")     # 48 points, or 53 with the nose
    return frames, truth, head, np.asarray(labs, np.intp)


def errors(points: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(n_frames, n_points) distance to the truth in inter-ocular units."""
    from keyshape.base.schemes import load_scheme
    iod = load_scheme("contours48").interocular_distance(truth)
    return np.linalg.norm(points - truth, axis=-1) / iod[:, None]


def line(name: str, err: np.ndarray) -> str:
    nme = np.nanmean(err, 1)
    return (f"{name:34s} NME {np.nanmean(nme):.4f} p95 {np.nanpercentile(nme, 95):.4f} | "
            + " ".join(f"{g} {np.nanmean(err[:, i]):.4f}" for g, i in GROUPS.items()))


def track(model, frames) -> np.ndarray:
    from keyshape.tracker.fitting import Tracker, single_threaded
    t = Tracker(model)
    with single_threaded():
        return np.stack([t.step(f, i).points for i, f in enumerate(frames)])


def by_bins(err: np.ndarray, value: np.ndarray, edges, name: str) -> list[str]:
    out = [f"by {name}: frames, NME, " + ", ".join(GROUPS)]
    for a, b in zip(edges[:-1], edges[1:]):
        m = (value >= a) & (value < b)
        if m.any():
            out.append(f"  {a:+4.0f}..{b:+4.0f} {int(m.sum()):4d} {np.nanmean(err[m]):.4f}  "
                       + " ".join(f"{np.nanmean(err[m][:, i]):.4f}" for i in GROUPS.values()))
    return out


class DepthFrame:
    """The depth-aware model frame of a fitted 2D model's reference: ``image = P [X, Y, Z, 1]``, P (2, 4)."""

    def __init__(self, reference: np.ndarray, size: int):
        from scipy.interpolate import RBFInterpolator

        from keyshape.base.geometry import apply_affine, fit_similarity
        from keyshape.base.schemes import load_head_template
        pts, self.weights = load_head_template("contours48")
        both = np.vstack([pts, load_head_template("ibug68")[0][27:36]])      # + the generic face's nose
        front = np.column_stack([both[:, 0], -both[:, 1]])
        sim = fit_similarity(front[:48], reference)
        z = both[:, 2] * np.sqrt(abs(np.linalg.det(sim[:, :2])))
        z -= z[:48].mean()
        self.ref, self.z_pts = reference, z[:48]
        self.yy, self.xx = np.mgrid[0:size, 0:size].astype(np.float64)
        rbf = RBFInterpolator(apply_affine(sim, front), z, kernel="thin_plate_spline", smoothing=1.0)
        self.depth = rbf(np.column_stack([self.xx.ravel(), self.yy.ravel()])).reshape(size, size)

    def fit(self, points: np.ndarray) -> np.ndarray:
        a = np.column_stack([self.ref, self.z_pts, np.ones(48)])
        w = np.sqrt(np.maximum(self.weights, 0.02))[:, None]
        return np.linalg.lstsq(a * w, points * w, rcond=None)[0].T

    def sample(self, gray: np.ndarray, p: np.ndarray) -> np.ndarray:
        mx = p[0, 0] * self.xx + p[0, 1] * self.yy + p[0, 2] * self.depth + p[0, 3]
        my = p[1, 0] * self.xx + p[1, 1] * self.yy + p[1, 2] * self.depth + p[1, 3]
        return cv2.remap(gray, mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).astype(np.float32)

    def to_model(self, p: np.ndarray, points: np.ndarray) -> np.ndarray:
        return np.linalg.solve(p[:, :2], (points - p[:, 3] - np.outer(self.z_pts, p[:, 2])).T).T

    def to_image(self, p: np.ndarray, shape: np.ndarray) -> np.ndarray:
        return shape @ p[:, :2].T + np.outer(self.z_pts, p[:, 2]) + p[:, 3]


def read_in_place(model, patch: np.ndarray, global_weight: float = 0.3) -> np.ndarray:
    """Model-frame shape of a patch: the global reading, each region read where it is (no refinement),
    blended as the tracker blends them."""
    c, _ = model.project(model.intensities(patch))
    shape = model.landmarks(c)
    for rm in model.region_models_:
        shape[rm.points] = (1 - global_weight) * rm.read(rm.crop(patch)) + global_weight * shape[rm.points]
    return shape


def oracles(model, frames, truth, labs) -> tuple[np.ndarray, np.ndarray]:
    """Truth-pose readings through the 2D affine frame and through a depth-aware frame (module docstring, 3)."""
    import keyshape.tracker.eigenpoints as ep
    from keyshape.base.geometry import apply_affine, fit_affine, procrustes_mean
    from keyshape.tracker.eigenpoints import AppearanceModel, Pyramid, warp_patch
    ref, size = model.reference_, model.patch_size_
    flat = np.stack([apply_affine(a, read_in_place(model, warp_patch(Pyramid(f), a, size)))
                     for f, a in ((f, fit_affine(ref, t)) for f, t in zip(frames, truth))])
    df = DepthFrame(ref, size)
    model_mean = procrustes_mean(truth[labs])
    # the same training, its affines replaced by the depth-aware frame (the reference is kept as is)
    with mock.patch.object(ep, "procrustes_mean", lambda labels: model_mean), \
            mock.patch.object(ep, "fit_affine", lambda r, lab: df.fit(lab)), \
            mock.patch.object(ep, "warp_patch", lambda pyr, p, s: df.sample(pyr[0], p)), \
            mock.patch.object(ep, "invert_affine", lambda p: p), \
            mock.patch.object(ep, "apply_affine", lambda p, lab: df.to_model(p, lab)):
        deep = AppearanceModel("contours48", rng=0).fit(list(frames[labs]), truth[labs])
    assert np.allclose(deep.reference_, ref)
    depth = np.stack([df.to_image(p, read_in_place(deep, df.sample(f, p)))
                      for f, p in ((f, df.fit(t)) for f, t in zip(frames, truth))])
    return flat, depth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", help="a bench/synth3d_accuracy.py work folder")
    ap.add_argument("--more-labels", action="store_true", help="also train on 24 and 48 labelled frames")
    a = ap.parse_args()
    from keyshape.tracker.eigenpoints import AppearanceModel
    from heldout import spread_frames
    work = Path(a.work)
    frames, truth, head, labs = load(work)
    yaw, pitch = head["head_yaw_deg"], head["head_pitch_deg"]
    print(f"take: yaw {yaw.min():+.1f}..{yaw.max():+.1f}, pitch {pitch.min():+.1f}..{pitch.max():+.1f} deg; "
          f"labelled frames' yaw {np.round(yaw[labs]).astype(int).tolist()}, pitch {np.round(pitch[labs]).astype(int).tolist()}")
    model = AppearanceModel("contours48", rng=0).fit(list(frames[labs]), truth[labs])
    pts = track(model, frames)
    err = errors(pts, truth)
    print(line("tracked (12 labels)", err))
    print("\n".join(by_bins(err, np.abs(yaw), [0, 5, 10, 15, 20, 25, 40], "|yaw|")))
    print("\n".join(by_bins(err, pitch, [-30, -10, -5, 0, 5, 10, 30], "pitch")))
    near = np.min(np.abs(np.arange(len(truth))[:, None] - labs[None]), 1)
    print("by frames from the nearest label: " + ", ".join(
        f"{lo}-{hi}: {np.nanmean(err[(near >= lo) & (near < hi)]):.4f}"
        for lo, hi in ((0, 1), (1, 5), (5, 15), (15, 40), (40, 10 ** 6)) if ((near >= lo) & (near < hi)).any()))
    from scipy.ndimage import uniform_filter1d
    d = pts - truth
    slow = uniform_filter1d(d, 9, axis=0)
    print(f"slow (9-frame mean) part {np.nanmean(errors(truth + slow, truth)):.4f}, "
          f"fast part {np.nanmean(errors(truth + d - slow, truth)):.4f}")
    flat, deep = oracles(model, frames, truth, labs)
    print(line("oracle pose, 2D affine frame", errors(flat, truth)))
    print(line("oracle pose, depth-aware frame", errors(deep, truth)))
    if a.more_labels:
        for k in (24, 48):
            extra = spread_frames(len(truth), k - len(labs), exclude=labs, min_gap=3, rng=0)
            lk = np.sort(np.r_[labs, extra])
            mk = AppearanceModel("contours48", rng=0).fit(list(frames[lk]), truth[lk])
            print(line(f"tracked ({k} labels)", errors(track(mk, frames), truth)))


if __name__ == "__main__":
    main()
