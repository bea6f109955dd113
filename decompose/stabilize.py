"""Head stabilisation: the head's 2D pose from the points that stay rigid with the skull.

Design notes and figures: docs/decompose.md, "Notes on the code", ``decompose/stabilize.py``.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError, NotFittedError
from keyshape.base.geometry import rigid_fit
from keyshape.decompose.defaults import HEAD_POSES  # noqa: F401  (3d, rigid, tracker)
from keyshape.decompose.head3d import HeadPose3D


def similarity_affines(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Per frame, the least-squares similarity ``dst_from_src`` as a (n_frames, 2, 3) affine.

    Parameters
    ----------
    src : (n_frames, n_points, 2) points per frame; frames with a NaN get the identity
    dst : (n_points, 2) where they should go

    Notes
    -----
    One batched Umeyama fit (:func:`~keyshape.base.geometry.rigid_fit`, scale included);
    ``dst ~ s R src + t`` minimises the squared distances in ``dst``'s frame.
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    out = np.broadcast_to(np.eye(2, 3), (len(src), 2, 3)).copy()
    ok = np.isfinite(src).all(axis=(1, 2))
    if ok.any():
        rot, trans, sc = rigid_fit(src[ok], np.broadcast_to(dst, src[ok].shape), scale=True)
        out[ok, :, :2] = sc[:, None, None] * rot
        out[ok, :, 2] = trans
    return out


class RigidStabilizer:
    """Remove the head motion the tracker's pose left in 2D shapes, from the points rigid with the skull.

    Parameters
    ----------
    points : indices of the scheme's rigid points (two or more; ``Scheme.rigid``)

    Attributes
    ----------
    reference_ : (n_rigid, 2) where the rigid points are put in every frame (per-point median
        over the frames given to :meth:`fit`, or set from a KEYS.json with :meth:`from_dict`)

    Examples
    --------
    >>> stab = RigidStabilizer(scheme.rigid).fit(shapes)        # doctest: +SKIP
    >>> stable = stab.transform(shapes)                           # doctest: +SKIP
    """

    def __init__(self, points: Sequence[int]):
        self.points = tuple(int(i) for i in points)

    def _check(self, shapes) -> np.ndarray:
        arr = np.asarray(shapes, np.float64)
        if len(self.points) < 2 or len(set(self.points)) != len(self.points):
            raise InputError(f"head stabilisation needs two or more distinct rigid points, got {list(self.points)}")
        if arr.ndim != 3 or arr.shape[2] != 2 or max(self.points) >= arr.shape[1] or min(self.points) < 0:
            raise InputError(f"shapes of shape {arr.shape} do not have the rigid points {list(self.points)}")
        return arr

    def fit(self, shapes: np.ndarray) -> "RigidStabilizer":
        """Learn ``reference_`` from (n_frames, n_points, 2) head-frame shapes (NaN rows: failed frames)."""
        arr = self._check(shapes)[:, list(self.points)]
        ok = np.isfinite(arr).all(axis=(1, 2))
        if not ok.any():
            raise InputError("no successful frame to stabilise the head on")
        ref = np.median(arr[ok], axis=0)
        if np.linalg.norm(ref - ref.mean(axis=0)) < 1e-9:
            raise InputError(f"the rigid points {list(self.points)} coincide: cannot stabilise the head on them")
        self.reference_ = ref
        return self

    def correction(self, shapes: np.ndarray) -> np.ndarray:
        """(n_frames, 2, 3) similarity ``stable_from_head`` of every frame (identity where a frame is NaN)."""
        if not hasattr(self, "reference_"):
            raise NotFittedError("this RigidStabilizer is not fitted yet: call fit(shapes) first")
        arr = self._check(shapes)
        return similarity_affines(arr[:, list(self.points)], self.reference_)

    def transform(self, shapes: np.ndarray) -> np.ndarray:
        """``shapes`` with each frame mapped by its :meth:`correction` (NaN rows stay NaN)."""
        arr = self._check(shapes)
        c = self.correction(arr)
        return np.einsum("tij,tpj->tpi", c[:, :, :2], arr) + c[:, None, :, 2]

    def to_dict(self) -> dict:
        """The KEYS.json ``head_pose`` entry: method, points and reference."""
        return {"method": "rigid", "points": list(self.points), "reference": np.round(self.reference_, 6).tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> "RigidStabilizer":
        """The stabiliser a KEYS.json ``head_pose`` entry describes (checked by its reader)."""
        out = cls(data["points"])
        out.reference_ = np.asarray(data["reference"], np.float64)
        return out

    def __repr__(self) -> str:
        return f"RigidStabilizer(points={list(self.points)})"


def head_pose_entry(stabilizer: RigidStabilizer | HeadPose3D | None) -> dict:
    """The KEYS.json ``head_pose`` entry of a stabiliser (``{"method": "tracker"}`` for None)."""
    return {"method": "tracker"} if stabilizer is None else stabilizer.to_dict()


def stabilizer_from_entry(entry: dict | RigidStabilizer | HeadPose3D | None) -> RigidStabilizer | HeadPose3D | None:
    """The stabiliser of a KEYS.json ``head_pose`` entry (None for ``tracker``); a stabiliser or
    None passes through, so callers may take either."""
    if isinstance(entry, dict):
        if entry.get("method") == "3d":
            return HeadPose3D.from_dict(entry)
        return RigidStabilizer.from_dict(entry) if entry.get("method") == "rigid" else None
    return entry
