"""Built-in demo targets from ICT-FaceKit expressions, made "as an artist would".

Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/targets/demo.py``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.formats.obj import Mesh
from keyshape.retarget.targets.target_set import TargetSet, name_key

DATA = Path(__file__).parents[1] / "data" / "ict_face.npz"


@dataclass
class ExpressionSet:
    """A neutral face and named expression deltas.

    Attributes
    ----------
    neutral : (n_vertices, 3) float64, centimetres
    triangles : (n_triangles, 3) int
    names : list of n_expressions names (ICT-FaceKit: ARKit names with ``_L``/``_R``)
    deltas : (n_expressions, n_vertices, 3) float64, ``expression - neutral``
    landmarks : (68,) vertex indices in the Multi-PIE 68-landmark order
    """

    neutral: np.ndarray
    triangles: np.ndarray
    names: list
    deltas: np.ndarray
    landmarks: np.ndarray

    def coefficients(self, coeffs: Mapping[str, float]) -> np.ndarray:
        """(n_expressions,) vector from a ``{name: c}`` dict (names matched case-insensitively,
        ``_L``/``Left`` alike). Raises :class:`InputError` naming an unknown expression."""
        index = {name_key(n): i for i, n in enumerate(self.names)}
        c = np.zeros(len(self.names))
        for k, v in coeffs.items():
            i = index.get(name_key(k))
            if i is None:
                raise InputError(f"unknown expression {k!r}; known: {', '.join(self.names)}")
            if not np.isfinite(v):
                raise InputError(f"expression {k!r}: coefficient {v} is not finite")
            c[i] += float(v)
        return c

    def shape(self, coeffs: Mapping[str, float]) -> np.ndarray:
        """``neutral + sum_j c_j delta_j`` for one ``{name: c}`` dict: (n_vertices, 3)."""
        return self.neutral + np.tensordot(self.coefficients(coeffs), self.deltas, axes=1)

    def shapes(self, coeffs: Sequence[Mapping[str, float]]) -> np.ndarray:
        """Many combinations at once (one product): (n_shapes, n_vertices, 3)."""
        c = np.stack([self.coefficients(x) for x in coeffs]) if len(coeffs) else np.zeros((0, len(self.names)))
        return self.neutral + (c @ self.deltas.reshape(len(self.names), -1)).reshape(len(c), *self.neutral.shape)

    @property
    def mesh(self) -> Mesh:
        return Mesh(self.neutral, [t for t in self.triangles])


def load_expressions(path: str | Path | None = None) -> ExpressionSet:
    """Load the shipped subset (default) or another npz of the same layout."""
    path = require_file(DATA if path is None else path, "expression set (.npz)")
    with np.load(path) as d:
        missing = {"neutral", "triangles", "names", "deltas"} - set(d.files)
        if missing:
            raise InputError(f"expression set lacks {sorted(missing)}", path)
        return ExpressionSet(d["neutral"].astype(np.float64), d["triangles"].astype(np.intp),
                             [str(n) for n in d["names"]], d["deltas"].astype(np.float64),
                             d["landmarks"].astype(np.intp) if "landmarks" in d.files else np.zeros(0, np.intp))


# Multi-PIE 68-landmark indices of each decompose region (iBUG order: brows 17-26, eyes 36-47, mouth 48-67)
LANDMARK_REGIONS = {"mouth": list(range(48, 68)), "eyes": list(range(17, 27)) + list(range(36, 48)),
                    "pupils": list(range(36, 48))}


def demo_regions(expressions: ExpressionSet | None = None, names: Sequence[str] = ("mouth", "eyes")) \
        -> dict[str, np.ndarray]:
    """Region vertex groups on the shipped face (decompose's region names), from its 68 landmark vertices:
    ready for :meth:`retarget.targets.retargeter.Retargeter.fit` (``regions=``)."""
    ex = load_expressions() if expressions is None else expressions
    if len(ex.landmarks) != 68:
        raise InputError("this expression set has no 68 landmark vertices")
    unknown = [n for n in names if n not in LANDMARK_REGIONS]
    if unknown:
        raise InputError(f"unknown regions {unknown}; known: {', '.join(LANDMARK_REGIONS)}")
    return {n: ex.landmarks[LANDMARK_REGIONS[n]] for n in names}


def demo_targets(key_coeffs: Mapping[str, Mapping[str, float]], expressions: ExpressionSet | None = None,
                 neutral_coeffs: Mapping[str, float] | None = None) -> TargetSet:
    """Targets for key shapes given their expression coefficients.

    Parameters
    ----------
    key_coeffs : ``{"mouth_0": {"jawOpen": 0.7, ...}, "eyes_0": {...}, ...}``, one entry per weight
        column in column order
    expressions : default :func:`load_expressions`
    neutral_coeffs : coefficients of the target neutral. ``keyshape decompose`` fits weights relative
        to the sequence's *mean* shape, so the matching target neutral is the target of that mean
        face: pass the mean of the hidden coefficients over the frames (default: the rest face, all 0).

    Returns
    -------
    TargetSet with columns/names the keys, neutral and mesh set (ready for :class:`Retargeter`).
    """
    ex = load_expressions() if expressions is None else expressions
    cols = list(key_coeffs)
    shapes = ex.shapes([key_coeffs[c] for c in cols])
    neutral = ex.shape(neutral_coeffs or {})
    return TargetSet(cols, cols, shapes, [DATA] * len(cols), neutral, ex.mesh.with_vertices(neutral))


def write_demo_targets(folder: str | Path, key_coeffs: Mapping[str, Mapping[str, float]],
                       expressions: ExpressionSet | None = None,
                       neutral_coeffs: Mapping[str, float] | None = None) -> Path:
    """Write one OBJ per key shape (``<column>.obj``) and ``neutral.obj`` into ``folder`` atomically,
    the input ``keyshape retarget --targets folder`` reads."""
    from keyshape.base.files import atomic_dir
    from keyshape.base.formats.obj import write_obj
    ts = demo_targets(key_coeffs, expressions, neutral_coeffs)
    with atomic_dir(folder, kind="targets") as tmp:
        write_obj(tmp / "neutral.obj", ts.mesh)
        for c, s in zip(ts.columns, ts.shapes):
            write_obj(tmp / f"{c}.obj", ts.mesh, s)
    return Path(folder)
