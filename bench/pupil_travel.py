"""How far the tracked pupils travel (issue 23): each pupil in its eye's frame, against a reference.

The pupil's offset from the midpoint of its eye's corners, along the corners' line (x) and across it
(y), in eye widths: what ``decompose/gaze.py`` (Eq. 1) turns into the gaze's yaw and pitch. Printed per
eye and axis: the gain (least-squares slope of the tracked offset on the reference's; 1 = the true
travel), Pearson's r and the RMS of the difference (means removed).

- ``synth WORK [TRACKS]``: a ``bench/synth3d_accuracy.py`` work folder; the reference is the take's exact
  landmarks (``take/truth.csv``), TRACKS defaults to ``WORK/tracks.csv``.
- ``real TRACKS REFERENCES``: real footage; the reference is MediaPipe FaceMesh's iris centres (points 468,
  473) in the eye frame of its own corners (33/133, 362/263), from ``../shared/data/video/references/``.
  Not a truth: an independent reading. Frames whose tracked lid gap is under 0.6 of its median are left out
  (a closing lid moves both readings of the iris).

    PYTHONPATH=. python bench/pupil_travel.py synth WORK [TRACKS]
    PYTHONPATH=. python bench/pupil_travel.py real TRACKS REFERENCES
"""
from __future__ import annotations

import argparse

import numpy as np

#: per eye (image-left, image-right): contours48's corners and pupil, upper and lower lid middles, and
#: MediaPipe FaceMesh's corners and iris centre (image-left corner first, as contours48's)
EYES = (("image-left eye", (10, 14, 26), (12, 16), (33, 133, 468)),
        ("image-right eye", (18, 22, 27), (20, 24), (362, 263, 473)))


def eye_frame(c0: np.ndarray, c1: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(T, 2) offsets of points ``p`` from the corners' midpoint, along and across ``c0 -> c1``, in its widths."""
    d = c1 - c0
    w = np.linalg.norm(d, axis=-1)
    u = d / w[:, None]
    q = p - (c0 + c1) / 2
    return np.column_stack([(q * u).sum(1) / w, (q[:, 1] * u[:, 0] - q[:, 0] * u[:, 1]) / w])


def travel(est: np.ndarray, ref: np.ndarray) -> dict:
    """Gain, r and RMS difference (means removed) of each column of ``est`` against ``ref``'s."""
    out = {}
    for j, ax in enumerate("xy"):
        ok = np.isfinite(est[:, j]) & np.isfinite(ref[:, j])
        a, t = est[ok, j] - est[ok, j].mean(), ref[ok, j] - ref[ok, j].mean()
        out[ax] = (float(t @ a / (t @ t)), float(np.corrcoef(a, t)[0, 1]), float(np.sqrt(np.mean((a - t) ** 2))))
    return out


def line(name: str, res: dict, extra: str = "") -> str:
    return f"{name}: " + ", ".join(f"{ax} gain {g:.2f} r {r:.3f} rms {e:.4f}" for ax, (g, r, e) in res.items()) + extra


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="mode", required=True)
    s = sub.add_parser("synth", help="against a 3D synthetic take's truth")
    s.add_argument("work")
    s.add_argument("tracks", nargs="?")
    r = sub.add_parser("real", help="against MediaPipe's irises on real footage")
    r.add_argument("tracks")
    r.add_argument("references")
    a = ap.parse_args()
    from keyshape.base.formats.tracks import read_tracks
    if a.mode == "synth":
        truth = read_tracks(f"{a.work}/take/truth.csv").points
        pts = read_tracks(a.tracks or f"{a.work}/tracks.csv").points
        for name, (c0, c1, p), _, _ in EYES:
            print(line(name, travel(eye_frame(pts[:, c0], pts[:, c1], pts[:, p]),
                                    eye_frame(truth[:, c0], truth[:, c1], truth[:, p]))))
    else:
        mp = np.load(a.references)["mediapipe478"]
        pts = read_tracks(a.tracks).points
        n = min(len(mp), len(pts))
        pts, mp = pts[:n], mp[:n]
        for name, (c0, c1, p), (up, lo), (m0, m1, mpp) in EYES:
            gap = np.linalg.norm(pts[:, up] - pts[:, lo], axis=-1)
            est = eye_frame(pts[:, c0], pts[:, c1], pts[:, p])
            est[~(gap > 0.6 * np.nanmedian(gap))] = np.nan
            print(line(name, travel(est, eye_frame(mp[:, m0], mp[:, m1], mp[:, mpp])),
                       f" ({int(np.isfinite(est[:, 0]).sum())} open frames)"))


if __name__ == "__main__":
    main()
