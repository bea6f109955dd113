"""A small rig from the shipped ICT-FaceKit subset, written as a rig folder (``keyshape animate``'s example, the tests')."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from keyshape.base.formats.obj import Mesh, write_obj


def ict_subset_rig(folder: str | Path, names=None, step: int = 1) -> tuple[Path, Path]:
    """Write a small blendshape rig made from the shipped ICT-FaceKit subset (``retarget/data/ict_face.npz``:
    the face skin, 9,409 vertices) into ``folder`` (``neutral.obj`` and one OBJ per expression, ICT-FaceKit's
    names) and its contours48 landmark JSON beside it; return ``(folder, landmarks)``.

    ``names``: the expressions to write (default all 53). The landmarks are ICT-FaceKit's shipped
    correspondence, but for the two pupils (eyeball vertices, not in the subset), put on the eye corners:
    keep the ``pupils`` region out of keys for this rig. A test's rig, needing no ``../shared``.
    """
    from keyshape.base.formats.poses import read_rig_landmarks, write_rig_landmarks
    from keyshape.base.schemes import load_scheme
    from keyshape.retarget.targets.demo import load_expressions
    from keyshape.retarget.rig.model import DATA, ICT_N_VERTICES

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ex = load_expressions()
    mesh = Mesh(ex.neutral, list(ex.triangles))
    write_obj(folder / "neutral.obj", mesh)
    for j, n in enumerate(ex.names):
        if names is None or n in names:
            write_obj(folder / f"{n}.obj", mesh, ex.neutral + ex.deltas[j])
    _, W = read_rig_landmarks(DATA / "ict_landmarks_contours48.json", ICT_N_VERTICES)
    a, b = load_scheme("contours48").inter_ocular
    points = []
    for i, row in enumerate(W):
        nz = np.flatnonzero(row)
        if nz.max() >= ex.neutral.shape[0]:                   # a pupil: onto an eye corner
            nz = np.flatnonzero(W[a if len(points) % 2 == 0 else b])
            row = W[a if len(points) % 2 == 0 else b]
        points.append(int(nz[0]) if len(nz) == 1 else [[int(v), float(row[v])] for v in nz])
    lm = folder.parent / f"{folder.name}_landmarks.json"
    write_rig_landmarks(lm, "contours48", ex.neutral.shape[0], points)
    return folder, lm
