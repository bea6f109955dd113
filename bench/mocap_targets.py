"""Targets for the mocap benchmarks and their tests: another face of ICT-FaceKit's topology, and the AnimFace take's
target markers on ICT-FaceKit (bench/mocap_accuracy.py, bench/mocap_animface.py, tests/test_mocap_pipeline.py)."""
from __future__ import annotations

import numpy as np

from keyshape.base.errors import require_file
from keyshape.data_synth.mocap import FACE_SKIN, FaceKit


def identity_face(kit: FaceKit, coeffs=(3.0, -2.0, 2.0, 1.5), scale: float = 1.05) -> np.ndarray:
    """A realistically different face with the same topology (data README's recipe)."""
    from keyshape.base.formats.obj import read_obj_vertices

    v = kit.neutral.copy()
    for i, c in enumerate(coeffs):
        p = require_file(kit.folder / f"identity{i:03d}.obj", "ICT-FaceKit identity")
        v += c * (read_obj_vertices(p, len(v)) - kit.neutral)
    centre = kit.neutral[:FACE_SKIN].mean(axis=0)
    return centre + scale * (v - centre)


def animface_target_markers(kit: FaceKit, labels, neutral_mm) -> dict:
    """Target markers on ICT for the AnimFace take's labels (real data, ``mocap/animface``).

    The source neutral markers are carried onto the ICT face by a similarity fit on nine
    hand-matched landmarks (nose top and tip, eye and mouth corners, chin), then snapped to
    the nearest face-skin vertex: a stand-in for the hand placement of section 5.1.
    """
    from keyshape.base.geometry import rigid_fit

    lm = kit.neutral[kit.landmarks]
    pairs = {"NoseTop": 27, "NoseHead": 30, "Leye_Outside": 45, "Reye_Outside": 36, "Mouth_Lend": 54,
             "Mouth_Rend": 48, "Chin": 8, "Leye_Inside": 42, "Reye_Inside": 39}
    src = np.array([neutral_mm[labels.index(k)] for k in pairs])
    dst = lm[list(pairs.values())]
    rot, trans, sc = rigid_fit(src, dst[None], scale=True)
    carried = sc[0] * neutral_mm @ rot[0].T + trans[0]
    skin = kit.neutral[:9409]
    out = {}
    for lab, p in zip(labels, carried):
        out[lab] = skin[np.argmin(np.linalg.norm(skin - p, axis=1))]
    return out
