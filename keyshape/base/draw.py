"""Drawing landmark contours on frames and laying frames out in contact sheets.

Used wherever a person checks shapes by eye: synthetic ground truth previews,
tracking overlays, key-shape sheets and labelling pages.
"""
from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from keyshape.base.schemes import Scheme

# one colour (BGR) per contour family; unknown contours get the default
_COLOURS = {"brow": (40, 200, 255), "eye": (255, 200, 40), "pupil": (60, 60, 255), "lip_outer": (80, 255, 80),
            "lip_inner": (200, 120, 255), "jaw": (200, 200, 200), "nose": (0, 170, 255)}


def _colour(name: str) -> tuple[int, int, int]:
    return next((c for key, c in _COLOURS.items() if name.startswith(key)), (255, 255, 255))


def draw_shape(image: np.ndarray, points: np.ndarray, scheme: Scheme, colour: tuple[int, int, int] | None = None,
               thickness: int = 1, numbers: bool = False) -> np.ndarray:
    """Return a copy of ``image`` (gray or BGR uint8) with ``points`` (n_points, 2) drawn as the scheme's contours.

    Points that are NaN are skipped. Coordinates are sub-pixel accurate
    (drawn with 4 fractional bits).
    """
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    pts = np.asarray(points, dtype=np.float64)
    shift = 4
    for name, idx in scheme.contours.items():
        c = colour or _colour(name)
        p = pts[list(idx)]
        ok = np.isfinite(p).all(axis=1)
        if not ok.any():
            continue
        q = np.round(p * (1 << shift)).astype(np.int32)
        if len(idx) == 1:
            if ok[0]:
                cv2.circle(out, tuple(q[0]), 3 << shift, c, thickness, cv2.LINE_AA, shift)
            continue
        if ok.all():
            cv2.polylines(out, [q.reshape(-1, 1, 2)], scheme.closed[name], c, thickness, cv2.LINE_AA, shift)
        for j in np.flatnonzero(ok):
            cv2.circle(out, tuple(q[j]), 1 << shift, c, -1, cv2.LINE_AA, shift)
    if numbers:
        for i, (x, y) in enumerate(pts):
            if np.isfinite([x, y]).all():
                cv2.putText(out, str(i), (int(x) + 2, int(y) - 2), cv2.FONT_HERSHEY_PLAIN, 0.6, (255, 255, 255), 1)
    return out


def contact_sheet(images: Sequence[np.ndarray], captions: Sequence[str] | None = None, columns: int = 4,
                  tile_width: int = 320, pad: int = 6, background: int = 32) -> np.ndarray:
    """Lay ``images`` (BGR or gray, any sizes) out in a grid of equal-width tiles with captions.

    Returns a BGR uint8 image.
    """
    if not len(images):
        raise ValueError("contact_sheet needs at least one image")
    tiles = []
    for k, im in enumerate(images):
        im = im if im.ndim == 3 else cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)
        h = int(round(im.shape[0] * tile_width / im.shape[1]))
        t = cv2.resize(im, (tile_width, h), interpolation=cv2.INTER_AREA)
        if captions is not None:
            cv2.rectangle(t, (0, 0), (tile_width, 20), (0, 0, 0), -1)
            cv2.putText(t, str(captions[k]), (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(t)
    th = max(t.shape[0] for t in tiles)
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    sheet = np.full((rows * (th + pad) + pad, columns * (tile_width + pad) + pad, 3), background, np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, columns)
        y, x = pad + r * (th + pad), pad + c * (tile_width + pad)
        sheet[y:y + t.shape[0], x:x + tile_width] = t
    return sheet


def crop_around(image: np.ndarray, points: np.ndarray, margin: float = 0.35) -> tuple[np.ndarray, np.ndarray]:
    """Crop ``image`` to the box around ``points`` enlarged by ``margin``; return (crop, points in the crop)."""
    p = np.asarray(points, dtype=np.float64)
    p_ok = p[np.isfinite(p).all(axis=1)]
    lo, hi = p_ok.min(axis=0), p_ok.max(axis=0)
    size = (hi - lo).max() * (1 + 2 * margin)
    centre = (lo + hi) / 2
    x0, y0 = np.floor(centre - size / 2).astype(int)
    x1, y1 = np.ceil(centre + size / 2).astype(int)
    h, w = image.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    return image[y0:y1, x0:x1], p - [x0, y0]
