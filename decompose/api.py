"""The decompose stage's in-memory layer, with the product's defaults.

``keyshape select`` and ``keyshape decompose`` (``decompose/cli.py``: argument parsing and files),
:mod:`keyshape.api`, ``keyshape batch`` and ``keyshape demo`` all call these functions and take
their defaults from here (:mod:`keyshape.decompose.defaults`, re-exported), so a default changes in
one place. They take and
return arrays and never open files.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import Scheme, load_scheme, scheme_for_n_points
from keyshape.decompose.regions import (RegionKeys, available_regions, decompose_region, drop_near_duplicates,
                                        face_rest_frame, head_shapes, select_region)
from keyshape.decompose.defaults import (HEAD_POSE, HEAD_POSES, METHOD, METHODS, MIN_KEY_DISTANCE,  # noqa: F401
                                         NEUTRAL_FRAME, RIDGE, SEED, SMOOTH_LAMBDA, SOLVER, SOLVERS)
from keyshape.decompose.stabilize import head_pose_entry
from keyshape.decompose.take import Take, take_fps  # noqa: F401  (the take, fitted once)


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


def parse_neutral_frame(value: int | str | None) -> int | str | None:
    """``neutral_frame`` as :func:`select_keys` takes it: a frame number, ``"auto"`` or None (``"mean"``)."""
    if value is None or value == "mean":
        return None
    if value == "auto":
        return "auto"
    try:
        return int(value)
    except (TypeError, ValueError):
        raise InputError(f"--neutral-frame must be a frame number, 'auto' or 'mean', got {value!r}") from None


def select_keys(tracks: Tracks | Sequence[Tracks], k: int | None, method: str = METHOD,
                regions: Sequence[str] | None = None, scheme: str | Scheme | None = None, seed: int = SEED,
                source=None, progress: bool = False, head: str = HEAD_POSE,
                neutral_frame: int | str | None = NEUTRAL_FRAME) -> tuple[Scheme, list[RegionKeys], dict]:
    """Choose ``k`` key shapes per region from ``tracks`` (see :func:`~keyshape.decompose.regions.select_region`).

    The product's defaults live here (``keyshape select``, :func:`keyshape.api.select`, ``keyshape
    batch`` and ``keyshape demo`` all take them from this signature).

    Parameters
    ----------
    tracks : one take's :class:`Tracks`, or several takes of one actor (one key set for all of
        them: the keys' ``frames`` are then each take's own frame numbers and ``takes`` says which
        take, as ``keyshape select`` with several files writes them)
    k : key shapes per region (None only for ``method="hull2"``)
    method : selector, default ``greedy`` (best in the project's measurements; ``spread`` is the paper's)
    regions : default all the scheme can form; scheme : default the built-in one with as many points
    seed : seed of kmeans/random/greedy; source : names the tracks in errors
    progress : show the greedy selector's progress on stderr
    head : how the head pose is taken out (:func:`~keyshape.decompose.regions.head_shapes`):
        ``3d`` (the head's 3D pose removed, :class:`~keyshape.decompose.head3d.HeadPose3D`), ``rigid`` (a 2D
        similarity on the scheme's rigid points) or ``tracker`` (its pose alone); default :data:`HEAD_POSE`
    neutral_frame : what the weights are relative to: ``"auto"`` (the actor's most relaxed frame,
        one for the whole face, the default), a frame number (one take only), or None / ``"mean"``
        (the take's mean shape, the paper's centring)

    Returns
    -------
    the scheme, the keys and the KEYS.json ``head_pose`` entry that goes with them
    """
    many = not isinstance(tracks, Tracks)
    takes = list(tracks) if many else [tracks]
    if not takes:
        raise InputError("no tracks to select key shapes from")
    if k is None and method != "hull2":
        raise InputError(f"-k is required for --method {method}")
    if k is not None and k < 1:
        raise InputError(f"-k {k}: need at least 1 key shape per region")
    nf = parse_neutral_frame(neutral_frame)
    if len(takes) > 1 and nf not in (None, "auto"):
        raise InputError("--neutral-frame F is ambiguous with several tracks files: use auto")
    if len(takes) > 1:
        tracks = concat_tracks(takes)
        take = np.concatenate([np.full(t.n_frames, i) for i, t in enumerate(takes)])
        orig_frame = np.concatenate([t.frame for t in takes])
    else:
        tracks = takes[0]
    sch = tracks_scheme(tracks, scheme, source)
    shapes, stab = head_shapes(tracks, sch, head, source)
    regions = list(regions or available_regions(sch))
    try:
        rest = face_rest_frame(tracks, shapes, sch, regions) if nf in (None, "auto") else None
        chosen = [drop_near_duplicates(select_region(tracks, sch, r, k, method, rng=seed, shapes=shapes,
                                                     neutral_frame=nf, progress=progress, rest_frame=rest),
                                       MIN_KEY_DISTANCE) for r in regions]
    except InputError as exc:
        if source is None:
            raise
        raise InputError(str(exc), source) from None
    if len(takes) > 1:                # rows were numbered 0..n-1: back to (take, frame)
        for rk in chosen:
            rk.takes = take[rk.frames]
            rk.frames = orig_frame[rk.frames]
            rk.rest_frame = int(orig_frame[rk.rest_frame])
    return sch, chosen, head_pose_entry(stab)


def decompose_keys(tracks: Tracks, regions: Sequence[RegionKeys], solver: str = SOLVER,
                   smooth_lambda: float = SMOOTH_LAMBDA, ridge: float = RIDGE, source=None,
                   head_pose: dict | None = None) -> tuple[list[str], np.ndarray]:
    """Per-frame weights of every region's key shapes: (column names ``REGION_K``, weights (n_frames, n_keys)).

    The product's defaults live here: ``solver="smooth"`` (NNLS with a temporal smoothness term, ``smooth_lambda``
    0.1) and ``ridge=0.03`` (Tikhonov shrinkage against tracking noise; docs/benchmarks.md). ``head_pose``: the
    keys' KEYS.json ``head_pose`` entry; every frame's head is taken out the same way the keys' was (default:
    the tracker's pose alone).
    """
    if solver not in SOLVERS:
        raise InputError(f"unknown solver {solver!r}: use one of {', '.join(SOLVERS)}")
    for name, v in (("--smooth-lambda", smooth_lambda), ("--ridge", ridge)):
        if not (np.isfinite(v) and 0 <= v <= 1e6):
            raise InputError(f"{name} {v}: must be a finite number from 0 to 1e6")
    shapes, _ = head_shapes(tracks, tracks_scheme(tracks, None, source), head_pose or "tracker", source)
    names, cols = [], []
    for rk in regions:
        cols.append(decompose_region(tracks, rk, solver, smooth_lambda, shapes=shapes, ridge=ridge))
        names += rk.names
    return names, np.concatenate(cols, axis=1)
