"""Automatic rig landmarks against the truth of remeshed ICT-FaceKit rigs (issue 39).

For each test rig (``bench/remesh_rig.py``: the shipped face decimated to ~40% of its vertices in a
shuffled order; ``plain``, the same in metres and Z-up, and other faces: ``reshape`` 0.6 and 1.0 cm of
other proportions with other artists' shapes; ``mask0.6``: such a face cut to its front, as ARKit's
face mesh; ``arkit``: that mask in metres, Z-up, with ARKit's shape names), prints the largest distance (cm, ICT's scale) of the
found landmarks from the true ones per group, in the neutral and under every shape (with ``--points``, each
point's, and the shape it is largest in); with ``--tracks``
and ``--keys`` (a real take's, e.g. cap12_edit or franck), also the correlation r of each checked curve
solved with the found landmarks against the curves solved with the true ones (``keyshape solve``).

Usage::

    python bench/rig_landmarks_accuracy.py [--work /tmp/rig_lm_bench] [--points] [--more] [--tracks T.csv --keys K.json]
"""
from __future__ import annotations

import argparse
import contextlib
import io
from pathlib import Path

import numpy as np

GROUPS = {"brows": range(0, 10), "eyes": range(10, 26), "pupils": range(26, 28), "outer lips": range(28, 40),
          "inner lips": range(40, 48)}
CHECKED = ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "browInnerUp_R")
RIGS = {"plain": dict(seed=3), "m_zup": dict(seed=3, units="m", up="z"), "face0.6": dict(seed=8, reshape=0.6),
        "face1.0": dict(seed=5, reshape=1.0), "face1.0b": dict(seed=7, reshape=1.0),
        "mask0.6": dict(seed=8, reshape=0.6, mask=True),
        "arkit": dict(seed=8, reshape=0.6, mask=True, arkit=True, units="m", up="z")}
#: more faces (``--more``): others of 1.0 and 0.8 cm, an ARKit-named mask of 1.0 cm, an ARKit-style mask in metres, Z-up
MORE = {"face1.0c": dict(seed=11, reshape=1.0), "face1.0d": dict(seed=12, reshape=1.0), "face0.8": dict(seed=13, reshape=0.8),
        "mask1.0": dict(seed=14, reshape=1.0, mask=True, arkit=True),
        "arkit0.6": dict(seed=15, reshape=0.6, mask=True, arkit=True, units="m", up="z")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/rig_lm_bench")
    ap.add_argument("--tracks", default=None)
    ap.add_argument("--keys", default=None)
    ap.add_argument("--points", action="store_true", help="each point's largest error and the shape it is in")
    ap.add_argument("--more", action="store_true", help="five more faces (MORE)")
    a = ap.parse_args()
    from keyshape.base.formats.poses import read_rig_landmarks
    from keyshape.base.formats.weights import read_weights
    from keyshape.cli import main as cli
    from remesh_rig import remeshed_ict_rig
    from keyshape.retarget.rig.model import found_landmarks, load_rig

    work = Path(a.work)
    for name, kw in ({**RIGS, **MORE} if a.more else RIGS).items():
        r = remeshed_ict_rig(work / name, **kw) if not (work / f"{name}_landmarks.json").is_file() else \
            {"rig": work / name, "landmarks": work / f"{name}_landmarks.json", "scale": 0.01 if "units" in kw else 1.0}
        rig = load_rig(r["rig"], cache=False)
        _, truth = read_rig_landmarks(r["landmarks"])
        found = found_landmarks(rig, "contours48").W
        posed = np.concatenate([rig.neutral[None], rig.neutral + rig.deltas])
        err = np.linalg.norm(np.einsum("pv,svc->spc", found - truth, posed), axis=-1) / r["scale"]
        cells = [f"{g} {err[:, list(ix)].max():.3f}" for g, ix in GROUPS.items()]
        line = f"{name:9s} {rig.n_vertices} vertices: max error (cm) {', '.join(cells)}"
        if a.points:
            shape = ["neutral", *rig.names]
            line += "\n  " + " ".join(f"{p}:{err[:, p].max():.3f}({shape[err[:, p].argmax()]})" for p in range(err.shape[1]))
        if a.tracks and a.keys:
            out = {}
            for kind, lm in (("true", ["--landmarks", str(r["landmarks"])]), ("auto", [])):
                path = work / f"{name}_{kind}.csv"
                with contextlib.redirect_stdout(io.StringIO()):
                    assert cli(["solve", a.tracks, "--keys", a.keys, "--rig", str(r["rig"]), *lm, "-o", str(path),
                                "--overwrite"]) == 0
                _, cols, values, _ = read_weights(path)
                out[kind] = {c: values[:, j] for j, c in enumerate(cols)}
            rs = [np.corrcoef(out["true"][n], out["auto"][n])[0, 1] for n in CHECKED]
            line += "; curves r " + ", ".join(f"{n} {x:.3f}" for n, x in zip(CHECKED, rs))
        print(line, flush=True)


if __name__ == "__main__":
    main()
