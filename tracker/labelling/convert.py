"""Convert iBUG-68 points to the ``contours48`` scheme.

Each brow, lid and lip of iBUG-68 is resampled to evenly spaced points by arc length between its corners along a
chord-length cubic spline through its points (each lip's middle point kept at iBUG's mid-lip point, so that it does
not slide when the head turns); each pupil is the dark iris blob inside the eye contour (needs the image; else the
contour's centroid). The layout: docs/formats.md, docs/label.md.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from keyshape.base.errors import InputError

# iBUG-68 polylines in contours48 order (image-left first; eyes and lips start
# at their image-left corner, upper curve to the right corner, then lower back).
IBUG_BROWS = ((17, 18, 19, 20, 21), (22, 23, 24, 25, 26))
IBUG_EYES = (((36, 37, 38, 39), (39, 40, 41, 36)), ((42, 43, 44, 45), (45, 46, 47, 42)))
IBUG_LIP_OUTER = ((48, 49, 50, 51, 52, 53, 54), (54, 55, 56, 57, 58, 59, 48))
IBUG_LIP_INNER = ((60, 61, 62, 63, 64), (64, 65, 66, 67, 60))


def resample_curve(points: np.ndarray, n: int, n_dense: int = 200, anchor: int | None = None) -> np.ndarray:
    """``n`` points evenly spaced by arc length along the curve through ``points`` (m, 2).

    The first and last points are kept exactly; the curve is a cubic spline in
    chord length (a straight line for 2 points). With ``anchor`` (an index into
    ``points``, ``n`` odd), the middle output point is ``points[anchor]`` and the
    others are evenly spaced by arc length on each side of it.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise InputError(f"a curve needs (m>=2, 2) points, got {pts.shape}")
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])  # drop repeated points
    pts, seg = pts[keep], seg[keep[1:]]
    if len(pts) < 2:
        return np.repeat(pts[:1], n, axis=0)
    t = np.concatenate([[0.0], np.cumsum(seg)])
    dense_t = np.linspace(0.0, t[-1], n_dense)
    if len(pts) == 2:
        dense = pts[0] + (dense_t / t[-1])[:, None] * (pts[1] - pts[0])
    else:
        dense = CubicSpline(t, pts, bc_type="natural")(dense_t)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    if anchor is not None and n % 2 == 1 and n >= 3 and 0 < int(anchor) < len(points) - 1 and keep.all():
        a = int(anchor)
        s_mid = float(np.interp(t[a], dense_t, arc))       # arc length of the anchor on the curve
        h = n // 2
        s = np.concatenate([np.linspace(0.0, s_mid, h + 1), np.linspace(s_mid, arc[-1], h + 1)[1:]])
    else:
        a = None
        s = np.linspace(0.0, arc[-1], n)
    out = np.column_stack([np.interp(s, arc, dense[:, 0]), np.interp(s, arc, dense[:, 1])])
    out[0], out[-1] = pts[0], pts[-1]
    if a is not None:
        out[n // 2] = pts[a]
    return out


def _closed(p68: np.ndarray, upper: tuple, lower: tuple, n_side: int, anchored: bool = False) -> np.ndarray:
    """Corner, n_side upper points, corner, n_side lower points (right to left).

    ``anchored``: each curve's middle iBUG point (odd-length polylines) is kept as its middle point.
    """
    up = resample_curve(p68[list(upper)], n_side + 2, anchor=len(upper) // 2 if anchored else None)
    lo = resample_curve(p68[list(lower)], n_side + 2, anchor=len(lower) // 2 if anchored else None)
    return np.concatenate([up[:-1], lo[:-1]])  # lower starts at the right corner, ends at left


def find_pupil(gray: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Centre of the dark iris blob inside the closed eye contour ``eye`` (k, 2).

    Pixels inside the contour darker than its 30th percentile (after a light
    blur) form the iris; the largest such connected blob gives the centre,
    weighted by darkness. Falls back to the contour's centroid when the eye is
    too small or closed (fewer than 6 pixels inside).
    """
    import cv2  # noqa: PLC0415

    eye = np.asarray(eye, dtype=np.float64)
    centroid = eye.mean(axis=0)
    h, w = gray.shape[:2]
    lo = np.maximum(np.floor(eye.min(axis=0)).astype(int) - 2, 0)
    hi = np.minimum(np.ceil(eye.max(axis=0)).astype(int) + 3, [w, h])
    if np.any(hi - lo < 3):
        return centroid
    crop = gray[lo[1]:hi[1], lo[0]:hi[0]]
    if crop.ndim == 3:
        crop = cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)
    mask = np.zeros(crop.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(eye - lo).astype(np.int32)], 1)
    inside = mask.astype(bool)
    if inside.sum() < 6:
        return centroid
    smooth = cv2.GaussianBlur(crop.astype(np.float32), (3, 3), 0)
    vals = smooth[inside]
    dark = inside & (smooth <= np.percentile(vals, 30))
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(dark.astype(np.uint8), connectivity=8)
    if n_lab < 2:
        return centroid
    big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    ys, xs = np.nonzero(labels == big)
    wgt = (vals.max() - smooth[ys, xs]) + 1e-6
    return np.array([np.average(xs, weights=wgt), np.average(ys, weights=wgt)]) + lo


def ibug68_to_contours48(points68: np.ndarray, image: np.ndarray | None = None) -> np.ndarray:
    """Map one face's iBUG-68 points (68, 2) to ``contours48`` points (48, 2).

    Parameters
    ----------
    points68 : (68, 2) array
    image : array, optional
        The frame (gray or BGR) to find the pupils in; without it each pupil is
        its eye contour's centroid.
    """
    p = np.asarray(points68, dtype=np.float64)
    if p.shape != (68, 2):
        raise InputError(f"expected iBUG-68 points of shape (68, 2), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError("iBUG-68 points contain NaN or inf")
    gray = None
    if image is not None:
        import cv2  # noqa: PLC0415
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    brows = [resample_curve(p[list(b)], 5) for b in IBUG_BROWS]
    eyes = [_closed(p, up, lo, 3) for up, lo in IBUG_EYES]
    pupils = [find_pupil(gray, e) if gray is not None else e.mean(axis=0) for e in eyes]
    outer = _closed(p, *IBUG_LIP_OUTER, 5, anchored=True)
    inner = _closed(p, *IBUG_LIP_INNER, 3, anchored=True)
    return np.concatenate([brows[0], brows[1], eyes[0], eyes[1], pupils[0][None], pupils[1][None],
                           outer, inner])
