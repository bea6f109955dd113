"""Regenerate ``retarget/data/ict_landmarks_<scheme>.json``: which ICT-FaceKit vertices the scheme's points are.

Usage (from the repository root)::

    PYTHONPATH=. python bench/build_ict_landmarks.py [--source ../shared/data/ict-facekit]

From ICT-FaceKit's 68 Multi-PIE landmark vertices (``vertex_indices.json``, ``idx_to_landmark_verts``):
``ibug68`` as they are, ``contours48`` derived as docs/formats.md says (the rig's published iBUG-68 list);
the pupils are the eyeball vertex in front of the eye's centre (ICT-FaceKit turns its eyeballs with bones,
so the ``pupils`` region drives no shape).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _lid(neutral: np.ndarray, chain: list[int], fractions) -> list:
    """Weighted vertex pairs at arc-length ``fractions`` along the vertex polyline ``chain``."""
    p = neutral[chain]
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) / seg.sum()
    out = []
    for f in fractions:
        j = min(int(np.searchsorted(s, f, side="right")) - 1, len(chain) - 2)
        a = (f - s[j]) / (s[j + 1] - s[j])
        out.append([[int(chain[j]), round(1 - a, 6)], [int(chain[j + 1]), round(a, 6)]])
    return out


def _pupil(neutral: np.ndarray, eyeball: np.ndarray, centre: np.ndarray) -> int:
    near = eyeball[np.linalg.norm(neutral[eyeball, :2] - centre[:2], axis=1) < 0.3]
    return int(near[np.argmax(neutral[near, 2])])


def contours48(neutral: np.ndarray, lm: np.ndarray, eyeballs: tuple[np.ndarray, np.ndarray]) -> list:
    """The contours48 entries (image-left first, as the scheme orders them)."""
    pts: list = [int(v) for v in lm[17:27]]                                  # 0-9 brows
    f = [0.25, 0.5, 0.75]
    for e in (36, 42):                                                        # 10-17, 18-25 eyes
        c0, u1, u2, c1, l1, l2 = lm[e:e + 6]
        pts += [int(c0)] + _lid(neutral, [c0, u1, u2, c1], f) + [int(c1)] + _lid(neutral, [c1, l1, l2, c0], f)
    for e, eb in zip((36, 42), eyeballs):                                     # 26, 27 pupils
        pts.append(_pupil(neutral, eb, neutral[lm[e:e + 6]].mean(axis=0)))
    pts += [int(v) for v in lm[48:68]]                                        # 28-47 lips
    return pts


def build(source: Path, out_dir: Path) -> list[Path]:
    from keyshape.base.formats.obj import read_obj_vertices
    from keyshape.base.formats.poses import write_rig_landmarks

    meta = json.loads((source / "vertex_indices.json").read_text())
    lm = np.asarray(meta["idx_to_landmark_verts"])
    neutral = read_obj_vertices(source / "generic_neutral_mesh.obj")
    eyeballs = []
    for side in ("R", "L"):           # subject's right = image-left first
        d = np.linalg.norm(read_obj_vertices(source / f"eyeLookUp_{side}.obj") - neutral, axis=1)
        lid = np.linalg.norm(read_obj_vertices(source / f"eyeBlink_{side}.obj") - neutral, axis=1)
        still = np.flatnonzero((d < 1e-6) & (lid < 1e-6))
        still = still[still > 11248]                                          # not skin, head or neck
        eyeballs.append(still[neutral[still, 0] * (1 if side == "L" else -1) > 0])
    paths = [out_dir / "ict_landmarks_contours48.json", out_dir / "ict_landmarks_ibug68.json"]
    write_rig_landmarks(paths[0], "contours48", len(neutral), contours48(neutral, lm, tuple(eyeballs)))
    write_rig_landmarks(paths[1], "ibug68", len(neutral), [int(v) for v in lm])
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=str(REPO.parent / "shared" / "data" / "ict-facekit"))
    ap.add_argument("--out", default=str(REPO / "retarget" / "data"))
    a = ap.parse_args()
    for p in build(Path(a.source), Path(a.out)):
        print(p)


if __name__ == "__main__":
    main()
