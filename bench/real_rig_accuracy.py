"""Real footage onto the ICT-FaceKit rig: do the rig's curves follow what two independent landmarkers see?

No ARKit weights exist for real footage, but some curves have a plain 2D counterpart that
MediaPipe FaceMesh and dlib measure on every frame (``../shared/data/video/references/``):

=================  =====================================================================
rig curve          reference signal (per frame, in inter-ocular units of that landmarker)
=================  =====================================================================
eyeBlink_L / _R    closure of that eye: minus the lid gap over the eye's width
jawOpen            the inner-lip gap
browInnerUp        height of the inner brow ends above the eye-corner line (both sides)
browOuterUp_L / R  height of that brow's outer end above the eye-corner line
mouthSmile         mouth width (corner to corner), mean of both sides' smile curves
=================  =====================================================================

The chain is ``select -k 8 --region mouth --region eyes``, ``decompose``, ``pose`` and
``retarget --poses ... -o curves.csv`` with default settings, on tracks of
``bench/real_tracker_accuracy.py`` (fresh ``keyshape label --count 12`` labels); printed: Pearson r of
each curve with each landmarker's signal, and the same for the tracked points' own signal (the
most the curves can carry). Eyebrow heights and mouth width also move with head pitch and yaw, so
their r is a lower bound.

    python bench/real_rig_accuracy.py TRACKS.csv REFERENCES.npz [--rig ../shared/data/ict-facekit] [--work DIR]
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

#: (name, points) per landmarker; _L/_R are the subject's sides (the subject's left is image-right).
MP = {"eye_L": (386, 374, 362, 263), "eye_R": (159, 145, 33, 133), "iod": (33, 263), "lips": (13, 14),
      "corners": (61, 291), "brow_in": (107, 336), "brow_out_L": 300, "brow_out_R": 70,
      "eye_line": (33, 133, 362, 263)}
DLIB = {"eye_L": ((43, 44), (46, 47), 42, 45), "eye_R": ((37, 38), (40, 41), 36, 39), "iod": (36, 45),
        "lips": (62, 66), "corners": (48, 54), "brow_in": (21, 22), "brow_out_L": 26, "brow_out_R": 17,
        "eye_line": (36, 39, 42, 45)}
#: contours48 (keyshape's scheme): image-left eye 10-17, image-right eye 18-25 (corners 10/14, 18/22).
C48 = {"eye_L": (20, 24, 18, 22), "eye_R": (12, 16, 10, 14), "iod": (10, 22), "lips": (42, 46),
       "corners": (28, 34), "brow_in": (4, 5), "brow_out_L": 9, "brow_out_R": 0, "eye_line": (10, 14, 18, 22)}


def _pt(P: np.ndarray, idx) -> np.ndarray:
    return P[:, list(idx)].mean(axis=1) if isinstance(idx, tuple) else P[:, idx]


def signals(P: np.ndarray, m: dict) -> dict[str, np.ndarray]:
    """Per-frame 2D expression signals of points ``P`` (n_frames, n, 2) with the index map ``m``."""
    iod = np.linalg.norm(_pt(P, (m["iod"][0],)) - _pt(P, (m["iod"][1],)), axis=1)
    eye = P[:, list(m["eye_line"])]
    # the eye-corner line: through the corners' mean, along the outer-to-outer direction
    c0 = eye.mean(axis=1)
    d = _pt(P, (m["iod"][1],)) - _pt(P, (m["iod"][0],))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    up = np.stack([d[:, 1], -d[:, 0]], axis=1)             # image y down: "up" is the rotated -y

    def height(q):
        return ((q - c0) * up).sum(axis=1) / iod

    out = {}
    for side in ("L", "R"):
        u, lo, a, b = m[f"eye_{side}"]
        u = (u,) if not isinstance(u, tuple) else u
        lo = (lo,) if not isinstance(lo, tuple) else lo
        gap = np.linalg.norm(_pt(P, u) - _pt(P, lo), axis=1)
        width = np.linalg.norm(P[:, a] - P[:, b], axis=1)
        out[f"eyeBlink_{side}"] = -gap / width
        out[f"browOuterUp_{side}"] = height(P[:, m[f"brow_out_{side}"]])
    out["jawOpen"] = np.linalg.norm(P[:, m["lips"][0]] - P[:, m["lips"][1]], axis=1) / iod
    out["browInnerUp"] = height(_pt(P, m["brow_in"]))
    out["mouthSmile"] = np.linalg.norm(P[:, m["corners"][0]] - P[:, m["corners"][1]], axis=1) / iod
    return out


def rig_signal(curves: np.ndarray, names: list[str], key: str) -> np.ndarray:
    if key == "mouthSmile":
        return curves[:, [names.index("mouthSmile_L"), names.index("mouthSmile_R")]].mean(axis=1)
    if key == "browInnerUp":
        return curves[:, [names.index("browInnerUp_L"), names.index("browInnerUp_R")]].mean(axis=1)
    return curves[:, names.index(key)]


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else 0.0


def run_chain(tracks: Path, rig: Path, work: Path, extra_select=(), extra_pose=()) -> Path:
    from keyshape.cli import main
    keys, weights, poses, curves = (work / n for n in ("keys.json", "weights.csv", "poses.json", "curves.csv"))
    for argv in (["select", str(tracks), "-k", "8", "--region", "mouth", "--region", "eyes", "-o", str(keys),
                  *extra_select],
                 ["decompose", str(tracks), "--keys", str(keys), "-o", str(weights)],
                 ["pose", str(keys), "--rig", str(rig), "-o", str(poses), *extra_pose],
                 ["retarget", str(weights), "--poses", str(poses), "--rig", str(rig), "-o", str(curves),
                  "--overwrite"]):
        if main(argv) != 0:
            raise SystemExit(f"keyshape {argv[0]} failed")
    return curves


def score(tracks_path: Path, refs_path: Path, curves_path: Path) -> dict:
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.weights import read_weights
    tr = read_tracks(tracks_path)
    frames, names, curves, _ = read_weights(curves_path)
    refs = np.load(refs_path)
    ok = tr.success
    rows = {}
    own = signals(tr.points, C48)
    ref = {"mediapipe": signals(refs["mediapipe478"][tr.frame], MP), "dlib": signals(refs["dlib68"][tr.frame], DLIB)}
    for key in own:
        c = rig_signal(curves, list(names), key)
        rows[key] = {"curve~mediapipe": pearson(c[ok], ref["mediapipe"][key][ok]),
                     "curve~dlib": pearson(c[ok], ref["dlib"][key][ok]),
                     "track~mediapipe": pearson(own[key][ok], ref["mediapipe"][key][ok])}
    return rows


def table(rows: dict) -> str:
    cols = list(next(iter(rows.values())))
    out = [f"{'curve':14s}" + "".join(f"{c:>18s}" for c in cols)]
    for k, v in rows.items():
        out.append(f"{k:14s}" + "".join(f"{v[c]:>18.3f}" for c in cols))
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tracks")
    ap.add_argument("references")
    ap.add_argument("--rig", default=str(REPO.parent / "shared" / "data" / "ict-facekit"))
    ap.add_argument("--work", default=None, help="folder for keys, weights, poses and curves (default: temporary)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(a.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        curves = run_chain(Path(a.tracks), Path(a.rig), work)
        print(f"{Path(a.tracks).name} onto {Path(a.rig).name}: Pearson r of each rig curve with the landmarkers' "
              "2D signal (track~mediapipe: the tracked points' own signal, the most the curves can carry)")
        print(table(score(Path(a.tracks), Path(a.references), curves)))


if __name__ == "__main__":
    main()
