"""Head motion from the tracked 2D affine pose (section 5 of 004_119ba07521a9af0b.txt).

The paper did not estimate 3D head motion: "only scaled 2D translation and
rotation are applied to the output motion". The tracker's pose is the affine
``image_from_model`` ``[x_img, y_img] = A [x, y] + t``; its 2x2 part is reduced
to the nearest similarity ``s R(theta)`` (Frobenius norm): for
``A = [[a, b], [c, d]]``, ``s cos(theta) = (a + d) / 2`` and
``s sin(theta) = (c - b) / 2``; any shear or anisotropy is dropped.

The root transform is relative to a reference frame ``r``: rendering the
model with frame ``r``'s camera after the root transform gives frame ``t``'s
image, ``S_r root(m) + t_r = S_t m + t_t``, so
``root(m) = (s_t / s_r) R(theta_t - theta_r) m + S_r^{-1} (t_t - t_r)``:
scale ``s_t / s_r``, rotation ``theta_t - theta_r`` about the model origin and a
translation in model units. Image y points down and mesh y up, so the output
rotates about +z by ``-(theta_t - theta_r)`` and moves by ``(dx, -dy, 0)`` times
``units_per_model`` (mesh units per model unit).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from keyshape.base.errors import InputError


@dataclass
class HeadMotion:
    """Per-frame root transform (glTF conventions).

    Attributes
    ----------
    translation : (n_frames, 3) float64, mesh units
    rotation : (n_frames, 4) float64 unit quaternions (x, y, z, w), about +z
    scale : (n_frames, 3) float64, uniform
    angle : (n_frames,) float64, radians about +z (mesh frame, y up)
    """

    translation: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    angle: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.translation)

    def matrices(self) -> np.ndarray:
        """(n_frames, 4, 4) homogeneous matrices T R S."""
        n = self.n_frames
        c, s = np.cos(self.angle), np.sin(self.angle)
        m = np.zeros((n, 4, 4))
        k = self.scale[:, 0]
        m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = k * c, -k * s, k * s, k * c
        m[:, 2, 2] = k
        m[:, :3, 3] = self.translation
        m[:, 3, 3] = 1.0
        return m

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """Bake the motion into ``(n_frames, n_vertices, 3)`` vertices (only when asked)."""
        m = self.matrices()
        return np.einsum("fij,fvj->fvi", m[:, :3, :3], vertices) + m[:, None, :3, 3]


def similarity(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest similarity of each affine ``image_from_model`` pose: (scale, angle, translation).

    ``pose``: (n_frames, 2, 3). Returns ``s`` (n_frames,), ``theta`` (n_frames,) radians in
    image axes, ``t`` (n_frames, 2) pixels.
    """
    p = np.asarray(pose, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (2, 3):
        raise InputError(f"pose: expected shape (n_frames, 2, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError(f"pose: frame {int(np.flatnonzero(~np.isfinite(p).all(axis=(1, 2)))[0])} is not finite")
    pc = (p[:, 0, 0] + p[:, 1, 1]) / 2
    ps = (p[:, 1, 0] - p[:, 0, 1]) / 2
    s = np.hypot(pc, ps)
    if np.any(s <= 0):
        raise InputError(f"pose: frame {int(np.flatnonzero(s <= 0)[0])} has zero scale")
    return s, np.arctan2(ps, pc), p[:, :, 2].copy()


def head_motion(pose: np.ndarray, reference: int = 0, units_per_model: float = 1.0) -> HeadMotion:
    """Root transform of every frame relative to frame ``reference`` (see module docstring).

    Parameters
    ----------
    pose : (n_frames, 2, 3) affine ``image_from_model`` (``keyshape.base.formats.tracks.Tracks.pose``)
    reference : frame index whose pose is the rest pose (identity transform)
    units_per_model : mesh units per model-frame unit, scales the translation
    """
    s, th, t = similarity(pose)
    n = len(s)
    if not -n <= reference < n:
        raise InputError(f"reference frame {reference} outside 0..{n - 1}")
    sr, thr, tr = s[reference], th[reference], t[reference]
    c, si = np.cos(-thr), np.sin(-thr)
    d = (t - tr) @ np.array([[c, -si], [si, c]]).T / sr        # S_r^{-1} (t_t - t_r), image axes
    translation = np.stack([d[:, 0], -d[:, 1], np.zeros(n)], axis=1) * units_per_model
    angle = -(th - thr)
    angle = (angle + np.pi) % (2 * np.pi) - np.pi
    rotation = np.stack([np.zeros(n), np.zeros(n), np.sin(angle / 2), np.cos(angle / 2)], axis=1)
    scale = np.repeat((s / sr)[:, None], 3, axis=1)
    return HeadMotion(translation, rotation, scale, angle)


def hold_invalid(pose: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Copy of ``pose`` where frames that are not ``valid`` or not finite hold the last valid pose
    (the first valid one before any). Raises :class:`InputError` when no frame is valid."""
    p = np.array(pose, dtype=np.float64)
    ok = np.isfinite(p).all(axis=(1, 2))
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    if not ok.any():
        raise InputError("pose: no frame has a valid pose")
    idx = np.where(ok, np.arange(len(p)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.flatnonzero(ok)[0])
    return p[idx]
