"""The decompose stage's part of the Python API (:mod:`keyshape.api`): in-memory steps.

``keyshape select`` and ``keyshape decompose`` (``decompose/cli.py``), :mod:`keyshape.api` and
``keyshape batch`` all call these functions; they take and return arrays and never open files.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import Scheme, load_scheme, scheme_for_n_points
from keyshape.decompose.regions import (RegionKeys, available_regions, decompose_region, face_rest_frame, head_shapes,
                                        select_region)
from keyshape.decompose.stabilize import head_pose_entry


def concat_tracks(tracks: Sequence[Tracks]) -> Tracks:
    """Several takes' tracks as one sequence (frames renumbered 0..n-1 in the given order)."""
    tracks = list(tracks)
    if not tracks:
        raise InputError("no tracks to select key shapes from")
    n_points = {t.n_points for t in tracks}
    if len(n_points) > 1:
        raise InputError(f"tracks of different point counts {sorted(n_points)} cannot share one key set")
    n = sum(t.n_frames for t in tracks)
    cat = [np.concatenate([getattr(t, a) for t in tracks]) for a in ("time", "confidence", "success", "points",
                                                                      "pose")]
    return Tracks(np.arange(n), *cat)


def tracks_scheme(tracks: Tracks, scheme: str | Scheme | None = None, source=None) -> Scheme:
    """``scheme`` (default: the built-in scheme with as many points as ``tracks``), checked against it."""
    sch = load_scheme(scheme) if scheme is not None else scheme_for_n_points(tracks.n_points)
    if sch.n_points != tracks.n_points:
        raise InputError(f"scheme {sch.name!r} has {sch.n_points} points, the tracks {tracks.n_points}", source)
    return sch


def select_keys(tracks: Tracks, k: int | None, method: str = "spread", regions: Sequence[str] | None = None,
                scheme: str | Scheme | None = None, seed: int = 0, source=None, progress: bool = False,
                head: str = "3d") -> tuple[Scheme, list[RegionKeys], dict]:
    """Choose ``k`` key shapes per region from ``tracks`` (see :func:`~keyshape.decompose.regions.select_region`).

    ``regions`` default to all the scheme can form; ``source`` names the tracks file in errors;
    ``progress`` shows the greedy selector's progress on stderr; ``head``: how the head pose is
    taken out (:func:`~keyshape.decompose.regions.head_shapes`: ``3d``, the default, ``rigid`` or ``tracker``).
    Returns the scheme, the keys and the KEYS.json ``head_pose`` entry that goes with them.
    """
    sch = tracks_scheme(tracks, scheme, source)
    if k is None and method != "hull2":
        raise InputError(f"-k is required for --method {method}")
    shapes, stab = head_shapes(tracks, sch, head, source)
    regions = list(regions or available_regions(sch))
    try:
        rest = face_rest_frame(tracks, shapes, sch, regions)
        chosen = [select_region(tracks, sch, r, k, method, rng=seed, shapes=shapes, progress=progress,
                                rest_frame=rest)
                  for r in regions]
    except InputError as exc:
        if source is None:
            raise
        raise InputError(str(exc), source) from None
    return sch, chosen, head_pose_entry(stab)


def decompose_keys(tracks: Tracks, regions: Sequence[RegionKeys], solver: str = "nnls", smooth_lambda: float = 0.1,
                   ridge: float = 0.0, source=None, head_pose: dict | None = None) -> tuple[list[str], np.ndarray]:
    """Per-frame weights of every region's key shapes: (column names ``REGION_K``, weights (n_frames, n_keys)).

    ``head_pose``: the keys' KEYS.json ``head_pose`` entry; every frame's head is taken out the same
    way the keys' was (default: the tracker's pose alone, what a key set without the entry means).
    """
    shapes, _ = head_shapes(tracks, tracks_scheme(tracks, None, source), head_pose or "tracker", source)
    names, cols = [], []
    for rk in regions:
        cols.append(decompose_region(tracks, rk, solver, smooth_lambda, shapes=shapes, ridge=ridge))
        names += rk.names
    return names, np.concatenate(cols, axis=1)
