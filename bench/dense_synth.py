"""Dense synthetic facial performances from the ICT-FaceKit expressions (ground truth for 002's tables;
bench/bench_dense.py and tests/test_dense.py).

Each performance drives a handful of ICT-FaceKit expression targets with
smooth, seeded weight curves in [0, 1]; frame 0 is the neutral face, as the
rest face ``F^0`` of 002_dce09d5f5656b088.txt. Vertex order is the ICT
mesh's (26,719 points), so every point's true trajectory is known.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_dir
from keyshape.base.formats.obj import read_obj, read_obj_vertices

#: performance name -> expressions it drives (three performances, as 002's Slap/Smile/Stretch)
PERFORMANCES: dict[str, tuple[str, ...]] = {
    "talk": ("jawOpen", "mouthFunnel", "mouthPucker", "mouthClose", "mouthLowerDown_L", "mouthLowerDown_R",
             "mouthUpperUp_L", "mouthUpperUp_R"),
    "smile": ("mouthSmile_L", "mouthSmile_R", "cheekSquint_L", "cheekSquint_R", "eyeSquint_L", "eyeSquint_R",
              "mouthDimple_L", "mouthDimple_R"),
    "stretch": ("browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R", "eyeWide_L", "eyeWide_R",
                "jawOpen", "mouthStretch_L", "mouthStretch_R", "cheekPuff_L"),
}


@lru_cache(maxsize=4)
def _load(ict_dir: str, names: tuple[str, ...]):
    d = require_dir(ict_dir, "ICT-FaceKit folder")
    mesh = read_obj(d / "generic_neutral_mesh.obj", require_faces=True)
    deltas = np.stack([read_obj_vertices(d / f"{n}.obj", mesh.n_vertices) - mesh.vertices for n in names])
    return mesh, deltas


def expression_weights(n_frames: int, n_expressions: int, rng=None) -> np.ndarray:
    """Smooth weight curves (n_frames, n_expressions) in [0, 1], zero at frame 0.

    Each curve is ``sin^2`` of a seeded sum of two low-frequency sines, so
    expressions rise and fall a few times over the take.
    """
    rng = np.random.default_rng(rng)
    t = np.linspace(0.0, 1.0, n_frames)[:, None]
    f = rng.uniform(0.5, 2.0, size=(2, n_expressions))
    a = rng.uniform(0.3, 1.0, size=(2, n_expressions))
    ph = rng.uniform(0, 2 * np.pi, size=(1, n_expressions))
    s = a[0] * np.sin(np.pi * f[0] * t) + a[1] * np.sin(np.pi * f[1] * t + ph) - a[1] * np.sin(ph)
    w = np.sin(0.5 * np.pi * np.clip(s, -1, 1)) ** 2
    return w * rng.uniform(0.6, 1.0, size=(1, n_expressions))


def dense_sequence(ict_dir: str | Path, performance: str = "talk", n_frames: int = 60, rng=None,
                   noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A dense performance: (vertices (n_frames, n_vertices, 3) cm, triangles (n_tri, 3)).

    Parameters
    ----------
    ict_dir : folder holding ``generic_neutral_mesh.obj`` and the expression OBJs.
    performance : one of :data:`PERFORMANCES`.
    n_frames : number of frames (frame 0 is the neutral).
    rng : None, int or Generator; the same seed gives the same sequence.
    noise : standard deviation of Gaussian noise added to every point (cm), like scanner noise.
    """
    if performance not in PERFORMANCES:
        raise InputError(f"unknown performance {performance!r}; choose from {', '.join(PERFORMANCES)}")
    if n_frames < 2:
        raise InputError(f"n_frames must be at least 2, got {n_frames}")
    rng = np.random.default_rng(rng)
    mesh, deltas = _load(str(ict_dir), PERFORMANCES[performance])
    w = expression_weights(n_frames, len(deltas), rng)
    frames = mesh.vertices[None] + np.einsum("fe,evd->fvd", w, deltas, optimize=True)
    if noise > 0:
        frames[1:] += rng.normal(scale=noise, size=frames[1:].shape)
    return frames, mesh.triangles


#: 12 registration landmarks, as positions in ICT's 68-landmark list (``idx_to_landmark_verts``):
#: outer/inner eye corners, nose tip, nostrils, mouth corners, upper/lower lip, chin
LANDMARKS68 = (36, 39, 42, 45, 30, 31, 35, 48, 54, 51, 57, 8)


def realistic_face(neutral: np.ndarray, identities: list, rng=None) -> np.ndarray:
    """A face realistically different from ``neutral``: ``neutral + sum c_i (identity_i - neutral)``.

    ``c_i`` uniform in [-3, 3] and the result scaled by a factor in [0.9, 1.1]
    about the origin (the advice of the shared data README); seeded by ``rng``.
    """
    rng = np.random.default_rng(rng)
    c = rng.uniform(-3, 3, len(identities))
    return (neutral + sum(ci * (x - neutral) for ci, x in zip(c, identities))) * rng.uniform(0.9, 1.1)
