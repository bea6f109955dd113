"""Gaze: each eye's yaw and pitch from its pupil relative to its corners, in the head's frame.

In the head-frame shapes (:class:`~keyshape.decompose.head3d.HeadPose3D`: the head's rotation
removed, the face brought to the front) a pupil that moves by ``d`` (in units of the eye's width
``w``, corner to corner) sideways from where it sits when the eye looks straight ahead has turned
the eyeball by

    ``yaw = asin(d_x w_cm / r)``,  ``pitch = asin(d_y w_cm / r)``                          (1)

with ``r`` = 1.2 cm the eyeball's radius and ``w_cm`` = 2.6 cm an adult eye's width (the 3D
face's, ICT-FaceKit); ``d`` is measured along the eye's corner-to-corner axis and across it. Straight
ahead is each eye's median pupil position over the take (a take looks mostly at the camera or the
scene ahead). While an eye is closed (its lid gap under half its median) its pupil is not seen:
the last open frame's gaze is held.

Signs follow the head's (:func:`keyshape.decompose.head3d.euler_angles`): yaw > 0 when the eye turns
to the actor's left, pitch > 0 when it looks down. The actor's left eye is the image-right eye
(contours48's ``eye_right`` and ``pupil_right``).
"""
from __future__ import annotations

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.schemes import Scheme

#: eyeball radius and eye width (cm) of Eq. 1
EYE_RADIUS_CM = 1.2
EYE_WIDTH_CM = 2.6
#: the scheme's (eye contour, pupil contour) of the actor's left and right eye (image right and left)
EYES = (("eye_right", "pupil_right"), ("eye_left", "pupil_left"))


def has_gaze(scheme: Scheme) -> bool:
    """Whether ``scheme`` has both eyes' contours with corners and both pupils."""
    return all(e in scheme.contours and p in scheme.contours for e, p in EYES)


def _corners(scheme: Scheme, eye: str) -> tuple[int, int, np.ndarray, np.ndarray]:
    pts = scheme.contours[eye]
    n = len(pts)
    a, b = pts[0], pts[n // 2]                            # image-left and image-right corners
    upper = np.array(pts[1:n // 2])
    lower = np.array(pts[n // 2 + 1:][::-1])
    return a, b, upper, lower


def gaze_angles(shapes: np.ndarray, scheme: Scheme) -> np.ndarray:
    """(n_frames, 4) left yaw, left pitch, right yaw, right pitch (radians, the actor's eyes) of
    head-frame shapes (n_frames, n_points, 2) (Eq. 1; NaN where a frame is NaN).

    Raises :class:`InputError` when the scheme has no pupils (``ibug68``: no gaze)."""
    if not has_gaze(scheme):
        raise InputError(f"scheme {scheme.name!r} has no pupils: no gaze (contours48 has them)")
    S = np.asarray(shapes, np.float64)
    out = np.full((len(S), 4), np.nan)
    ok = np.isfinite(S).all(axis=(1, 2))
    for j, (eye, pupil) in enumerate(EYES):
        a, b, upper, lower = _corners(scheme, eye)
        p = S[:, scheme.contours[pupil][0]]
        u = S[:, b] - S[:, a]
        w = np.linalg.norm(u, axis=-1)
        u = u / np.where(w > 0, w, 1.0)[:, None]
        n = np.stack([-u[:, 1], u[:, 0]], -1)                   # image y down: n points down
        mid = (S[:, a] + S[:, b]) / 2
        d = np.stack([((p - mid) * u).sum(-1), ((p - mid) * n).sum(-1)], -1) / np.where(w > 0, w, 1.0)[:, None]
        gap = np.linalg.norm(S[:, upper] - S[:, lower], axis=-1).mean(-1) / np.where(w > 0, w, 1.0)
        if not ok.any():
            continue
        open_ = ok & (gap >= 0.5 * np.median(gap[ok]))
        if not open_.any():
            open_ = ok
        d = d - np.median(d[open_], axis=0)
        idx = np.maximum.accumulate(np.where(open_, np.arange(len(S)), -1))
        idx[idx < 0] = int(np.flatnonzero(open_)[0])
        d = d[idx]
        ang = np.arcsin(np.clip(d * EYE_WIDTH_CM / EYE_RADIUS_CM, -1, 1))
        out[:, 2 * j:2 * j + 2] = ang
    out[~ok] = np.nan
    return out
