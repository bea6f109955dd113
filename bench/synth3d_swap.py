"""Which landmarks' tracking error costs the rig's curves on the 3D synthetic take (issue 23).

On a work folder of ``bench/synth3d_accuracy.py`` (its ``tracks.csv`` and ``take/truth.csv``) the README's
solve chain (``select -k 8 --region mouth --region eyes``, ``solve --rig``) is run on hybrid tracks, one
point group swapped at a time:

* ``tracks, GROUP from the truth``: the tracker's points with GROUP's replaced by the true ones: what
  GROUP's tracking error costs (the curves' r rises to the truth's where GROUP is the loss);
* ``truth, GROUP from the tracks``: the true points with GROUP's from the tracker: the same loss alone
  (no other tracking error, the head stabilised on the true eye corners unless GROUP holds them).

Printed per run: the scored curves' (jawOpen, both blinks, both smiles) Pearson r and gain against the
take's truth, and for the plain tracks the inner lips' opening (the mean vertical gap of the three facing
pairs across the eye line's normal, inter-ocular units) against the truth's. Groups: ``lips`` (28-47),
``eyes`` (the lids 10-25, whose corners are the stabilisation's rigid points), ``brows`` (0-9), ``pupils``
(26-27).

    PYTHONPATH=. python bench/synth3d_swap.py WORK [--groups lips eyes] [--rig DIR]
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
GROUPS = {"lips": range(28, 48), "eyes": range(10, 26), "brows": range(10), "pupils": range(26, 28)}
SCORED = ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R")
INNER_PAIRS = ((41, 47), (42, 46), (43, 45))          # contours48's inner lips: upper point, facing lower point


def r_gain(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Pearson r and the least-squares slope of ``est`` on ``truth`` (1 = true size)."""
    tc = truth - truth.mean()
    r = float(np.corrcoef(est, truth)[0, 1]) if est.std() > 0 and truth.std() > 0 else float("nan")
    return r, float(tc @ (est - est.mean()) / (tc @ tc))


def inner_opening(points: np.ndarray, iod: np.ndarray) -> np.ndarray:
    """(T,) the inner lips' mean gap across the eye corners' line, in inter-ocular units."""
    e = (points[:, 10] + points[:, 14]) / 2 - (points[:, 18] + points[:, 22]) / 2
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    normal = np.stack([-e[:, 1], e[:, 0]], axis=1)
    up, lo = (np.array(x) for x in zip(*INNER_PAIRS))
    return np.abs(((points[:, lo] - points[:, up]) * normal[:, None]).sum(-1)).mean(1) / iod


def solve_scores(tracks, truth_curves, folder: Path, name: str, rig: Path) -> dict:
    """The README chain on ``tracks`` (written to ``folder``); ``{curve: (r, gain)}`` of the scored curves."""
    from keyshape.base.formats.tracks import write_tracks
    from keyshape.base.formats.weights import read_weights
    from keyshape.cli import main
    p, keys, curves = folder / f"{name}.csv", folder / f"{name}_keys.json", folder / f"{name}_curves.csv"
    write_tracks(p, tracks)
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(["select", str(p), "-k", "8", "--region", "mouth", "--region", "eyes", "-o", str(keys)]) == 0
        assert main(["solve", str(p), "--keys", str(keys), "--rig", str(rig), "-o", str(curves)]) == 0
    rec = read_weights(curves)
    col, tcol = {n: j for j, n in enumerate(rec.names)}, {n: j for j, n in enumerate(truth_curves.names)}
    return {c: r_gain(rec.weights[:, col[c]], truth_curves.weights[:, tcol[c]]) for c in SCORED}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", help="a bench/synth3d_accuracy.py work folder (tracks.csv, take/)")
    ap.add_argument("--groups", nargs="+", choices=sorted(GROUPS), default=["lips", "eyes"])
    ap.add_argument("--rig", default=str(REPO.parent / "shared" / "data" / "ict-facekit"))
    a = ap.parse_args()
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.weights import read_weights
    from keyshape.base.schemes import load_scheme
    work = Path(a.work)
    tr, truth = read_tracks(work / "tracks.csv"), read_tracks(work / "take" / "truth.csv")
    tc = read_weights(work / "take" / "curves.csv")
    iod = load_scheme("contours48").interocular_distance(truth.points)
    r, g = r_gain(inner_opening(tr.points, iod), inner_opening(truth.points, iod))
    print(f"inner lips' opening, tracks against the truth: r {r:.3f} gain {g:.2f}")
    runs = [("tracks", tr.points), ("truth", truth.points)]
    for grp in a.groups:
        idx = list(GROUPS[grp])
        P = tr.points.copy()
        P[:, idx] = truth.points[:, idx]
        runs.append((f"tracks, {grp} from the truth", P))
        P = truth.points.copy()
        P[:, idx] = tr.points[:, idx]
        runs.append((f"truth, {grp} from the tracks", P))
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, P) in enumerate(runs):
            s = solve_scores(dataclasses.replace(tr, points=P), tc, Path(tmp), f"run{i}", Path(a.rig))
            print(f"{name:30s} " + ", ".join(f"{c} r {v[0]:.3f} g {v[1]:.2f}" for c, v in s.items()), flush=True)


if __name__ == "__main__":
    main()
