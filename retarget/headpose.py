"""Head motion from the tracked 2D affine pose (section 5 of 004_119ba07521a9af0b.txt).

Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/headpose.py``.
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
    rotation : (n_frames, 4) float64 unit quaternions (x, y, z, w): about +z for the 2D motion, any
        3D rotation for :func:`head_motion_3d`
    scale : (n_frames, 3) float64, uniform (1 for the 3D head: depth is a translation)
    angle : (n_frames,) float64, radians about +z (mesh frame, y up): the in-plane angle (the roll)
    angles : (n_frames, 3) float64 or None: yaw, pitch, roll in radians of the 3D head
        (:func:`keyshape.decompose.head3d.euler_angles`: yaw > 0 the actor turns to their left, pitch > 0
        looks down, roll > 0 tilts toward their right shoulder); None for the 2D motion
    """

    translation: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    angle: np.ndarray
    angles: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return len(self.translation)

    def matrices(self) -> np.ndarray:
        """(n_frames, 4, 4) homogeneous matrices T R S."""
        n = self.n_frames
        m = np.zeros((n, 4, 4))
        m[:, :3, :3] = quaternion_matrix(self.rotation) * self.scale[:, None, :]
        m[:, :3, 3] = self.translation
        m[:, 3, 3] = 1.0
        return m

    def take(self, rows) -> "HeadMotion":
        """The motion of some frames (an index array or slice)."""
        return HeadMotion(self.translation[rows], self.rotation[rows], self.scale[rows], self.angle[rows],
                          None if self.angles is None else self.angles[rows])

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """Bake the motion into ``(n_frames, n_vertices, 3)`` vertices (only when asked)."""
        m = self.matrices()
        return np.einsum("fij,fvj->fvi", m[:, :3, :3], vertices) + m[:, None, :3, 3]


def head_rotations_of(head: "HeadMotion | None") -> np.ndarray | None:
    """(n_frames, 3, 3) rotations of a head motion (the 3D head's, or the 2D motion's roll), or None."""
    if head is None:
        return None
    return quaternion_matrix(head.rotation)


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of (n, 4) unit quaternions (x, y, z, w)."""
    q = np.asarray(q, np.float64)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def matrix_quaternion(R: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (x, y, z, w), w >= 0, of (n, 3, 3) rotation matrices (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R, axis1=1, axis2=2)
    cand = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], 1)
    k = cand.argmax(1)
    q = np.zeros((len(R), 4))
    for i in range(4):                        # four cases, each vectorised over its frames
        m = k == i
        if not m.any():
            continue
        r = R[m]
        if i == 0:
            s = np.sqrt(1 + tr[m]) * 2
            q[m] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                             (r[:, 1, 0] - r[:, 0, 1]) / s, s / 4], 1)
        else:
            a, b, c = (i - 1), i % 3, (i + 1) % 3
            s = np.sqrt(np.maximum(1 + r[:, a, a] - r[:, b, b] - r[:, c, c], 1e-300)) * 2
            v = np.zeros((m.sum(), 4))
            v[:, a] = s / 4
            v[:, b] = (r[:, b, a] + r[:, a, b]) / s
            v[:, c] = (r[:, c, a] + r[:, a, c]) / s
            v[:, 3] = (r[:, c, b] - r[:, b, c]) / s
            q[m] = v
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def head_motion_3d(rotation: np.ndarray, translation: np.ndarray, angles: np.ndarray,
                   units: float = 1.0) -> HeadMotion:
    """The root transform of the 3D head (:meth:`keyshape.decompose.head3d.HeadPose3D.head_pose`).

    ``rotation`` (n, 3, 3) and ``translation`` (n, 3, cm from the zero frame) are in head axes (x the
    actor's left, y up, z out of the face toward the camera), which are a rig's and glTF's axes
    (ICT-FaceKit, ARKit: y up, the face looking down +z), so the node rotates by ``rotation`` about
    the rig's origin and moves by ``translation * units`` (mesh units per cm; depth is the z
    translation, never a scale). Failed frames (NaN) hold the last good pose.
    """
    R = np.asarray(rotation, np.float64)
    t = np.asarray(translation, np.float64)
    a = np.asarray(angles, np.float64)
    ok = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1) & np.isfinite(a).all(axis=1)
    if not ok.any():
        raise InputError("head pose: no frame has a valid pose")
    idx = np.maximum.accumulate(np.where(ok, np.arange(len(R)), -1))
    idx[idx < 0] = int(np.flatnonzero(ok)[0])
    R, t, a = R[idx], t[idx] * units, a[idx]
    return HeadMotion(t, matrix_quaternion(R), np.ones((len(R), 3)), a[:, 2].copy(), a)


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
