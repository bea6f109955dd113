"""Face regions, head-pose removal and per-region key shapes and weights.

The paper models the eye and mouth regions separately (section 5), and
animates the pupils as their own region. Regions here are built from the
landmark scheme's regions:

=========  ===================  ==========================
region     scheme regions       contours48 points
=========  ===================  ==========================
mouth      ``mouth``            28-47 (outer and inner lip)
eyes       ``eyes+brows``       0-25 (brows and eyelids)
pupils     ``pupils``           26-27
=========  ===================  ==========================

Key shapes must be expressions, not head motion: :func:`model_shapes` maps every
tracked frame into the model frame with the inverse of its ``image_from_model``
pose (``tracks.pose``) before anything is selected or decomposed.
"""
from __future__ import annotations

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.keys import REGIONS, RegionKeys
from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import Scheme
from keyshape.decompose.selectors import make_selector
from keyshape.decompose.weights import solve_weights

__all__ = ["REGIONS", "RegionKeys", "region_points", "available_regions", "model_shapes", "to_image",
           "select_region", "decompose_region"]


def region_points(scheme: Scheme, region: str) -> np.ndarray:
    """Point indices of ``region`` (``mouth``, ``eyes`` or ``pupils``) in ``scheme``."""
    if region not in REGIONS:
        raise InputError(f"unknown region {region!r}: use one of {', '.join(REGIONS)}")
    parts = REGIONS[region].split("+")
    missing = [p for p in parts if p not in scheme.regions]
    if missing:
        raise InputError(f"scheme {scheme.name!r} lacks region(s) {', '.join(missing)} needed for "
                         f"{region!r}; it has {', '.join(scheme.regions)}")
    return scheme.region(REGIONS[region])


def available_regions(scheme: Scheme) -> list[str]:
    """The regions of :data:`REGIONS` that ``scheme`` can form."""
    return [r for r, parts in REGIONS.items() if all(p in scheme.regions for p in parts.split("+"))]


def model_shapes(tracks: Tracks, path=None) -> np.ndarray:
    """Tracked points mapped to the model frame (head pose removed): (n_frames, n_points, 2).

    ``p_model = A^-1 (p_image - t)`` with ``[A | t] = tracks.pose`` (``image_from_model``).
    Failed frames (``success=0``) come back as NaN; NaN in a successful frame is an error.
    """
    pts = tracks.points
    ok = tracks.success
    bad = ok & ~np.isfinite(pts).all(axis=(1, 2))
    if bad.any():
        rows = np.flatnonzero(bad)
        raise InputError(f"frames {tracks.frame[rows[:5]].tolist()}{'...' if len(rows) > 5 else ''} are "
                         f"marked success=1 but have empty/NaN points: mark them success=0 or fill them", path)
    A = tracks.pose[:, :, :2]
    if np.any(np.abs(np.linalg.det(A[ok])) < 1e-12):
        raise InputError("a successful frame has a singular head pose (pose_a11..a22)", path)
    Ainv = np.linalg.inv(np.where(ok[:, None, None], A, np.eye(2)))
    out = np.einsum("tij,tpj->tpi", Ainv, pts - tracks.pose[:, None, :, 2])
    out[~ok] = np.nan
    return out


def to_image(model_pts: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Model-frame points (n_frames, n, 2) to the image with ``pose`` (n_frames, 2, 3)."""
    return np.einsum("tij,tpj->tpi", pose[:, :, :2], model_pts) + pose[:, None, :, 2]


def select_region(tracks: Tracks, scheme: Scheme, region: str, n_keys: int | None, method: str = "spread",
                  rng=None, shapes: np.ndarray | None = None, progress: bool = False) -> RegionKeys:
    """Choose ``n_keys`` key shapes of ``region`` from the successful frames of ``tracks``.

    Failed frames (``success=0``) are never candidates. ``shapes`` may pass the
    already computed :func:`model_shapes`.
    """
    idx = region_points(scheme, region)
    shapes = model_shapes(tracks) if shapes is None else shapes
    ok = np.flatnonzero(tracks.success)
    if n_keys is not None and n_keys > len(ok):
        raise InputError(f"cannot choose {n_keys} key shapes from {len(ok)} successful frames "
                         f"({tracks.n_frames - len(ok)} of {tracks.n_frames} failed)")
    sub = shapes[ok][:, idx]
    sel = make_selector(method, n_keys if n_keys is not None else 0, rng=rng, progress=progress,
                        desc=f"keyshape select {region}").fit(sub)
    from_frame = np.ones(len(sel.indices_), dtype=bool)
    if getattr(sel, "centre", "nearest") == "mean":
        from_frame[:] = False
    return RegionKeys(region, method, idx, tracks.frame[ok[sel.indices_]], sel.keys_, sel.neutral_, from_frame)


def decompose_region(tracks: Tracks, keys: RegionKeys, solver: str = "nnls", smooth_lambda: float = 0.1,
                     shapes: np.ndarray | None = None, ridge: float = 0.0) -> np.ndarray:
    """Weights (n_frames, n_keys) of ``keys`` for every frame of ``tracks``; failed frames interpolated."""
    shapes = model_shapes(tracks) if shapes is None else shapes
    if keys.points.max(initial=-1) >= shapes.shape[1]:
        raise InputError(f"key shapes of {keys.region!r} name point {keys.points.max()} but the tracks "
                         f"have {shapes.shape[1]} points")
    return solve_weights(shapes[:, keys.points], keys.keys, keys.neutral, solver=solver,
                         smooth_lambda=smooth_lambda, observed=tracks.success, ridge=ridge)
