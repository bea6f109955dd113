"""Gaze: each eye's yaw and pitch from its pupil relative to its corners, in the head's frame.

Eq. 1 turns a pupil's offset from where it sits looking straight ahead into the eyeball's angles, Eq. 2 models
the lids' pull on a tracked pupil during blinks (:class:`LidDrag`). Signs follow the head's: yaw > 0 when the eye
turns to the actor's left, pitch > 0 when it looks down.
The equations and the design: docs/decompose.md, "Notes on the code", ``decompose/gaze.py``.
"""
from __future__ import annotations

import numpy as np

from keyshape.base.errors import InputError, NotFittedError
from keyshape.base.schemes import Scheme

#: eyeball radius and eye width (cm) of Eq. 1
EYE_RADIUS_CM = 1.2
EYE_WIDTH_CM = 2.6
#: the scheme's (eye contour, pupil contour) of the actor's left and right eye (image right and left)
EYES = (("eye_right", "pupil_right"), ("eye_left", "pupil_left"))


def pupil_points(scheme: Scheme) -> list[int]:
    """Indices of the scheme's pupil points: each eye's pupil contour of :data:`EYES`, the right eye's first."""
    return [int(p) for _, pupil in EYES for p in scheme.contours.get(pupil, ())]


#: the longest blink (seconds): the brief part of the lids' closure that :class:`LidDrag` fits on
BLINK_S = 0.4
#: an eye whose lid gap is under this fraction of its median is shut (its pupil unseen: the gaze is held)
SHUT = 0.5


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


def _eye(S: np.ndarray, scheme: Scheme, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eye ``j`` of :data:`EYES` in head-frame shapes ``S`` (n_frames, n_points, 2): the pupil's offset
    ``d`` (n_frames, 2) from the corners' midpoint along and across the corner line (eye widths; across
    points down), the lid gap (eye widths), and the frame's axes ``u``, ``n`` scaled by the eye's width
    (n_frames, 2) each, so that the pupil is ``mid + d_x u + d_y n``."""
    eye, pupil = EYES[j]
    a, b, upper, lower = _corners(scheme, eye)
    p = S[:, scheme.contours[pupil][0]]
    u = S[:, b] - S[:, a]
    w = np.linalg.norm(u, axis=-1)
    w1 = np.where(w > 0, w, 1.0)
    n = np.stack([-u[:, 1], u[:, 0]], -1)                   # image y down: n points down
    mid = (S[:, a] + S[:, b]) / 2
    d = np.stack([((p - mid) * u).sum(-1), ((p - mid) * n).sum(-1)], -1) / (w1 ** 2)[:, None]
    gap = np.linalg.norm(S[:, upper] - S[:, lower], axis=-1).mean(-1) / w1
    return d, gap, u, n


def _closure(gap: np.ndarray) -> np.ndarray:
    """The lids' closure ``1 - gap / median(gap)`` over the finite frames (Eq. 2; 0 at the take's typical opening)."""
    fin = np.isfinite(gap)
    g0 = float(np.median(gap[fin])) if fin.any() else 1.0
    return 1.0 - gap / (g0 if g0 > 0 else 1.0)


class LidDrag:
    """The lids' pull on the tracked pupils during blinks (Eq. 2), fitted on a take and taken out of it.

    Parameters
    ----------
    fps : frames per second of the shapes
    blink_s : the longest blink, seconds (the closure's brief part: its peaks shorter than ``blink_s``, what a
        grey opening over ``blink_s`` takes away; the pupil's brief part for the fit: the pupil's offset less
        its running median over twice that)

    Attributes
    ----------
    coef_ : (2, 2) ``k`` per eye (rows as :data:`EYES`: the actor's left eye, then the right; columns
        along the corner line and across it, down), eye widths per unit of closure
    scheme_ : the scheme it was fitted with

    Examples
    --------
    >>> drag = LidDrag(fps=30.0).fit(shapes, scheme)          # doctest: +SKIP
    >>> angles = gaze_angles(drag.transform(shapes), scheme)  # doctest: +SKIP
    """

    def __init__(self, fps: float = 30.0, blink_s: float = BLINK_S):
        self.fps = fps
        self.blink_s = blink_s

    def _size(self) -> int:
        """Frames of the longest blink, plus one (the opening's structuring element)."""
        return max(1, int(round(self.blink_s * self.fps))) + 1

    def _blinks(self, c: np.ndarray) -> np.ndarray:
        """The brief part ``b`` of a closure ``c`` (n_frames,): ``c`` less its grey opening (NaN stays NaN)."""
        from scipy.ndimage import grey_opening
        out = np.full_like(c, np.nan)
        fin = np.isfinite(c)
        if fin.any():
            out[fin] = c[fin] - grey_opening(c[fin], size=self._size(), mode="nearest")
        return out

    def fit(self, shapes: np.ndarray, scheme: Scheme) -> "LidDrag":
        """Fit ``k`` on head-frame ``shapes`` (n_frames, n_points, 2) in time order (NaN frames skipped).

        ``k`` is the least-squares slope of the brief part of each pupil's offset (less its running median)
        on the brief part of its eye's closure (less its grey opening) over the frames the eye is open (lid gap at least :data:`SHUT` of its median); 0
        where the take has no brief closure or is shorter than two blinks.

        Raises :class:`InputError` when the scheme has no pupils or ``fps``/``blink_s`` are not positive."""
        from scipy.ndimage import median_filter
        if not has_gaze(scheme):
            raise InputError(f"scheme {scheme.name!r} has no pupils: no gaze (contours48 has them)")
        if not (np.isfinite(self.fps) and self.fps > 0 and np.isfinite(self.blink_s) and self.blink_s > 0):
            raise InputError(f"LidDrag: fps {self.fps} and blink_s {self.blink_s} must be positive")
        S = np.asarray(shapes, np.float64)
        ok = np.isfinite(S).all(axis=(1, 2))
        self.coef_ = np.zeros((2, 2))
        self.scheme_ = scheme
        if ok.sum() < 2 * self._size() + 1:
            return self
        for j in range(2):
            d, gap, _, _ = _eye(S[ok], scheme, j)
            c = _closure(gap)
            b = self._blinks(c)
            db = d - median_filter(d, size=(2 * self._size() + 1, 1), mode="nearest")
            use = c <= 1.0 - SHUT
            var = float(b[use] @ b[use])
            if var > 1e-12:
                self.coef_[j] = (b[use] @ db[use]) / var
        return self

    def transform(self, shapes: np.ndarray) -> np.ndarray:
        """A copy of head-frame ``shapes`` (n_frames, n_points, 2, time order) with each pupil moved back by
        the lids' pull ``k b_t`` (Eq. 2; ``b`` from these shapes' own lids)."""
        if not hasattr(self, "coef_"):
            raise NotFittedError("this LidDrag is not fitted yet: call fit(shapes, scheme) first")
        S = np.array(shapes, np.float64)
        for j, (_, pupil) in enumerate(EYES):
            _, gap, u, n = _eye(S, self.scheme_, j)
            b = np.nan_to_num(self._blinks(_closure(gap)))
            S[:, self.scheme_.contours[pupil][0]] -= b[:, None] * (self.coef_[j, 0] * u + self.coef_[j, 1] * n)
        return S

    def fit_transform(self, shapes: np.ndarray, scheme: Scheme) -> np.ndarray:
        """:meth:`fit` then :meth:`transform` on the same shapes."""
        return self.fit(shapes, scheme).transform(shapes)


def gaze_angles(shapes: np.ndarray, scheme: Scheme) -> np.ndarray:
    """(n_frames, 4) left yaw, left pitch, right yaw, right pitch (radians, the actor's eyes) of
    head-frame shapes (n_frames, n_points, 2) (Eq. 1; NaN where a frame is NaN). A take's lids' pull on
    its pupils is taken out beforehand by :class:`LidDrag`.

    Raises :class:`InputError` when the scheme has no pupils (``ibug68``: no gaze)."""
    if not has_gaze(scheme):
        raise InputError(f"scheme {scheme.name!r} has no pupils: no gaze (contours48 has them)")
    S = np.asarray(shapes, np.float64)
    out = np.full((len(S), 4), np.nan)
    ok = np.isfinite(S).all(axis=(1, 2))
    if not ok.any():
        return out
    for j in range(2):
        d, gap, _, _ = _eye(S, scheme, j)
        open_ = ok & (gap >= SHUT * np.median(gap[ok]))
        if not open_.any():
            open_ = ok
        d = d - np.median(d[open_], axis=0)
        idx = np.maximum.accumulate(np.where(open_, np.arange(len(S)), -1))
        idx[idx < 0] = int(np.flatnonzero(open_)[0])
        d = d[idx]
        out[:, 2 * j:2 * j + 2] = np.arcsin(np.clip(d * EYE_WIDTH_CM / EYE_RADIUS_CM, -1, 1))
    out[~ok] = np.nan
    return out


#: the shortest fixation (seconds) :func:`denoise_gaze` holds flat: fixations last 0.2-0.5 s and more
FIXATION_S = 0.3


def _tv1d(y: np.ndarray, lam: float) -> np.ndarray:
    """The 1D total-variation denoising of ``y`` (n,): ``argmin_x 1/2 |y - x|^2 + lam sum |x_{t+1} - x_t|``,
    exactly, by Condat's direct algorithm (L. Condat, "A direct algorithm for 1D total variation denoising",
    IEEE Signal Processing Letters 20(11), 2013; his C code line for line), one pass over the frames.
    """
    y = np.asarray(y, np.float64)
    n = len(y)
    x = y.copy()
    if n < 2 or lam <= 0:
        return x
    k = k0 = kminus = kplus = 0
    umin, umax = lam, -lam
    vmin, vmax = y[0] - lam, y[0] + lam
    while True:
        while k == n - 1:
            if umin < 0.0:
                x[k0:kminus + 1] = vmin
                k0 = kminus + 1
                k = kminus = k0
                vmin = y[k]
                umin = lam
                umax = vmin + umin - vmax
            elif umax > 0.0:
                x[k0:kplus + 1] = vmax
                k0 = kplus + 1
                k = kplus = k0
                vmax = y[k]
                umax = -lam
                umin = vmax + umax - vmin
            else:
                vmin += umin / (k - k0 + 1)
                x[k0:k + 1] = vmin
                return x
        umin += y[k + 1] - vmin
        if umin < -lam:
            x[k0:kminus + 1] = vmin
            k0 = kminus + 1
            k = kminus = kplus = k0
            vmin = y[k]
            vmax = vmin + 2 * lam
            umin, umax = lam, -lam
            continue
        umax += y[k + 1] - vmax
        if umax > lam:
            x[k0:kplus + 1] = vmax
            k0 = kplus + 1
            k = kminus = kplus = k0
            vmax = y[k]
            vmin = vmax - 2 * lam
            umin, umax = lam, -lam
        else:
            k += 1
            if umin >= lam:
                kminus = k
                vmin += (umin - lam) / (kminus - k0 + 1)
                umin = lam
            if umax <= -lam:
                kplus = k
                vmax += (umax + lam) / (kplus - k0 + 1)
                umax = -lam


def frame_noise(y: np.ndarray) -> float:
    """A robust estimate of the frame-to-frame noise's standard deviation of a signal ``y`` (n,) that holds
    still between rare jumps: the MAD of its first differences (their median taken out) over ``sqrt(2)``."""
    d = np.diff(np.asarray(y, np.float64))
    d = d[np.isfinite(d)]
    if not len(d):
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2))


def denoise_gaze(angles: np.ndarray, fps: float, head: np.ndarray | None = None,
                 fixation_s: float = FIXATION_S) -> np.ndarray:
    """A whole take's eye angles denoised where eye physiology says they hold still (offline only: it sees
    every frame).

    Each angle is taken to the world frame by adding the head's (``head``; None: the head frame), denoised there by
    1D total variation (:func:`_tv1d`: fixations flat, saccades' steps sharp) and taken back, with
    ``lam = sigma sqrt(L)``, ``sigma`` the frame-to-frame noise (:func:`frame_noise`) and ``L`` the frames of the
    shortest fixation (``fixation_s``): fixations of ``L`` frames and more come out flat, and a saccade of amplitude
    ``A`` between them keeps all but about ``2 lam / L`` of it.

    Parameters
    ----------
    angles : (n_frames, n_angles) eye angles in time order (:func:`gaze_angles`; NaN rows are left out)
    fps : frames per second
    head : (n_frames, n_angles) the head's angle matching each column (yaw for a yaw), or None
    fixation_s : seconds of the shortest fixation held flat

    Returns
    -------
    (n_frames, n_angles) denoised angles (NaN where ``angles`` is)
    """
    A = np.array(angles, np.float64)
    if A.ndim != 2:
        raise InputError(f"denoise_gaze: angles must be (n_frames, n_angles), got {A.shape}")
    if not (np.isfinite(fps) and fps > 0 and np.isfinite(fixation_s) and fixation_s >= 0):
        raise InputError(f"denoise_gaze: fps {fps} must be positive and fixation_s {fixation_s} >= 0")
    Hd = np.zeros_like(A) if head is None else np.asarray(head, np.float64)
    if Hd.shape != A.shape:
        raise InputError(f"denoise_gaze: head {Hd.shape} must match angles {A.shape}")
    ok = np.isfinite(A).all(axis=1) & np.isfinite(Hd).all(axis=1)
    out = np.full_like(A, np.nan)
    out[ok] = A[ok]
    L = fixation_s * fps
    for j in range(A.shape[1]):
        w = A[ok, j] + Hd[ok, j]
        out[ok, j] = _tv1d(w, frame_noise(w) * np.sqrt(L)) - Hd[ok, j]
    return out


def take_gaze(shapes: np.ndarray, scheme: Scheme, fps: float, head: np.ndarray | None = None,
              lid_drag: bool = True, denoise: bool = True) -> np.ndarray:
    """A whole take's eye angles from its head-frame shapes, offline: the lids' pull taken out of the pupils
    (:class:`LidDrag`, Eq. 2; ``lid_drag``), each eye's yaw and pitch (:func:`gaze_angles`, Eq. 1) and the
    take's fixations denoised in the world frame (:func:`denoise_gaze`; ``denoise``).

    Parameters
    ----------
    shapes : (n_frames, n_points, 2) head-frame shapes in time order (NaN rows: failed frames)
    scheme : their landmark scheme (:func:`has_gaze`)
    fps : frames per second
    head : (n_frames, >= 2) the head's yaw and pitch (radians, :func:`~keyshape.decompose.head3d.euler_angles`)
        that take the eye angles to the world frame for the denoising; None: the head frame (a 2D head)

    Returns
    -------
    (n_frames, 4) left yaw, left pitch, right yaw, right pitch in radians (NaN where a frame failed)
    """
    if lid_drag:
        shapes = LidDrag(fps=fps).fit_transform(shapes, scheme)
    g = gaze_angles(shapes, scheme)
    if not denoise:
        return g
    return denoise_gaze(g, fps, head=None if head is None else np.asarray(head)[:, [0, 1, 0, 1]])
