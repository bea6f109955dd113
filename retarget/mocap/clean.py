"""Marker cleaning: rigid head-motion removal and missing-marker rebuilding (001_7296bf6ea73cabea.txt, 5.1 end, 5.2).

Design notes and figures: docs/mocap.md, "Notes on the code", ``retarget/mocap/clean.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.geometry import apply_rigid, rigid_fit, robust_rigid_fit


def rigidity_scores(positions: np.ndarray) -> np.ndarray:
    """Per marker, the median over other markers of the std over frames of their distance.

    Markers that move with the skull keep their mutual distances: low score = rigid.
    """
    x = np.asarray(positions, dtype=np.float64)
    d = np.linalg.norm(x[:, :, None] - x[:, None, :], axis=3)     # (F, M, M), NaN in gaps
    sd = np.nanstd(d, axis=0) if np.isfinite(d).any() else np.full(d.shape[1:], np.nan)
    np.fill_diagonal(sd, np.nan)
    return np.nanmedian(sd, axis=1)


def choose_rigid_set(positions: np.ndarray, n_min: int = 4, fraction: float = 0.25) -> np.ndarray:
    """Indices of the most rigid markers (at least ``n_min``, about ``fraction`` of all)."""
    score = rigidity_scores(positions)
    m = len(score)
    k = min(m, max(n_min, int(round(fraction * m))))
    order = np.argsort(np.where(np.isfinite(score), score, np.inf))
    return np.sort(order[:k])


@dataclass
class RigidRemoval:
    """Result of :func:`remove_rigid_motion`.

    Attributes
    ----------
    positions : (n_frames, n_markers, 3) markers in the reference frame's head pose
    rot, trans : (n_frames, 3, 3), (n_frames, 3): ``head_frame_from_ref``
    rigid : (n_rigid,) marker indices used
    residual : (n_frames,) RMS residual of the rigid markers kept in the fit (file units)
    rejected : (n_frames, n_rigid) bool, rigid markers rejected as outliers in a frame
        (columns follow ``rigid``)
    threshold : the outlier distance used (file units)
    """

    positions: np.ndarray
    rot: np.ndarray
    trans: np.ndarray
    rigid: np.ndarray
    residual: np.ndarray
    rejected: np.ndarray | None = None
    threshold: float = np.inf

    def rejected_report(self, labels=None) -> list:
        """``[(label, n_frames, first_frame), ...]`` for every rigid marker rejected at least once."""
        if self.rejected is None:
            return []
        out = []
        for j in np.flatnonzero(self.rejected.any(axis=0)):
            m = int(self.rigid[j])
            out.append((labels[m] if labels is not None else m, int(self.rejected[:, j].sum()),
                        int(np.flatnonzero(self.rejected[:, j])[0])))
        return out


def remove_rigid_motion(positions, rigid=None, reference: int | np.ndarray = 0, robust_iters: int = 3,
                        labels=None, outlier_threshold: float | None = None) -> RigidRemoval:
    """Remove rigid head motion (001 section 5.1, last paragraph).

    With ``rigid`` (a head jig's markers) a least-squares rigid fit per frame; without, the most rigid markers
    (:func:`choose_rigid_set`) with ``robust_iters`` rounds of reweighting (a marker beyond twice its frame's median
    residual down-weighted). For a named rigid set (or with ``outlier_threshold``), a frame where a rigid marker lies
    beyond the threshold is refitted by RANSAC (:func:`keyshape.base.geometry.robust_rigid_fit`), the markers left
    out listed in ``rejected``.

    Parameters
    ----------
    positions : (n_frames, n_markers, 3)
    rigid : sequence of int, optional
    reference : int or (n_markers, 3)
        The frame (or pose) whose head pose the output keeps.
    outlier_threshold : float, optional
        Distance (file units) beyond which a rigid marker is an outlier in a frame. Default,
        with a named ``rigid`` set: 4 times the median residual of the rigid markers over the
        take, at least 1e-6 of the rigid set's RMS radius; for the estimated set: no rejection.
        ``np.inf``: off.
    """
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise InputError(f"positions: expected (n_frames, n_markers, 3), got {x.shape}")
    robust = rigid is None
    idx = choose_rigid_set(x) if robust else np.asarray(rigid, dtype=np.intp)
    if len(idx) < 3:
        raise InputError(f"rigid set: need at least 3 markers, got {len(idx)}")
    sub = x[:, idx]
    dead = ~np.isfinite(sub).all(axis=2).any(axis=0)
    if dead.all():
        name = [labels[i] for i in idx] if labels is not None else idx.tolist()
        raise InputError(f"rigid set {name}: every marker is missing in every frame")
    ref = x[reference, idx] if np.isscalar(reference) else np.asarray(reference, np.float64)[idx]
    if np.isscalar(reference) and not np.isfinite(ref).all():
        # reference frame has gaps in the rigid set: use the per-marker median after a first pass
        ref = np.where(np.isfinite(ref), ref, np.nanmedian(np.where(dead[:, None], 0.0, sub), axis=0))
    w = np.ones(sub.shape[:2])
    for _ in range(robust_iters if robust else 1):
        fit_w = w
        rot, trans, _s = rigid_fit(ref, sub, w)
        res = np.linalg.norm(apply_rigid(ref[None].repeat(len(x), 0), rot, trans) - sub, axis=2)
        if not robust:
            break
        med = np.nanmedian(res, axis=1, keepdims=True)
        cut = 2.0 * np.maximum(med, 1e-12)
        w = np.where(res > cut, cut / np.maximum(res, 1e-300), 1.0)
    bad = ~np.isfinite(rot).all(axis=(1, 2))
    if bad.any():
        raise InputError(f"rigid set: fewer than 3 visible markers in {bad.sum()} frame(s), first {np.flatnonzero(bad)[0]}; "
                         "fill gaps first or name a larger rigid set")
    thr = np.inf if outlier_threshold is None and robust else outlier_threshold
    if thr is None:
        radius = np.sqrt(np.mean(np.sum((ref - ref.mean(0)) ** 2, axis=1)))
        thr = max(4.0 * float(np.nanmedian(res)), 1e-6 * radius)
    rejected = np.zeros(sub.shape[:2], dtype=bool)
    if np.isfinite(thr) and (res > thr).any():
        rot2, trans2, rejected = robust_rigid_fit(ref, sub, thr, fit_w)
        redo = rejected.any(axis=1)
        rot[redo], trans[redo] = rot2[redo], trans2[redo]
        res[redo] = np.linalg.norm(apply_rigid(ref[None].repeat(redo.sum(), 0), rot[redo], trans[redo]) - sub[redo], axis=2)
    rms = np.sqrt(np.nanmean(np.where(rejected, np.nan, res) ** 2, axis=1))
    return RigidRemoval(apply_rigid(x, rot, trans, inverse=True), rot, trans, idx, rms, rejected, float(thr))


# ------------------------------------------------------------------------------- missing markers
def _runs(mask: np.ndarray):
    """(start, length) of every run of True in a 1-D bool array."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    starts = np.flatnonzero(d == 1)
    return starts, np.flatnonzero(d == -1) - starts


@dataclass
class GapReport:
    """Gaps found and what was done. ``filled``/``long``: lists of (label, first_frame, n_frames)."""

    filled: list = field(default_factory=list)
    long: list = field(default_factory=list)
    unfillable: list = field(default_factory=list)

    def __str__(self) -> str:
        lines = [f"{len(self.filled)} gap(s) filled, {len(self.long)} long gap(s), "
                 f"{len(self.unfillable)} left NaN"]
        lines += [f"  long gap: {lab} frames {s}..{s + n - 1} ({n} frames)" for lab, s, n in self.long]
        lines += [f"  left NaN: {lab} frames {s}..{s + n - 1}" for lab, s, n in self.unfillable]
        return "\n".join(lines)


def neighbours(reference: np.ndarray, k: int = 4) -> np.ndarray:
    """(n_markers, k) the ``k`` nearest other markers of each in the reference pose."""
    d = np.linalg.norm(reference[:, None] - reference[None], axis=2)
    np.fill_diagonal(d, np.inf)
    d[~np.isfinite(d)] = np.inf
    return np.argsort(d, axis=1)[:, :k]


def predict_from_frame(x: np.ndarray, reference: np.ndarray, target: int, frame_markers, anchor: int | None = None):
    """Positions of marker ``target`` in every frame from the rigid motion of ``frame_markers``.

    The target's reference position is carried by the best rigid fit of the
    ``frame_markers`` (reference -> frame). With ``anchor`` (section 5.2, inner lips) the
    offset ``target - anchor`` is expressed in that local frame and added to the anchor's
    current position: ``anchor_t + R_t (target_ref - anchor_ref)``.
    """
    fm = np.asarray(frame_markers, dtype=np.intp)
    rot, trans, _ = rigid_fit(reference[fm], x[:, fm])
    if anchor is None:
        return np.einsum("fij,j->fi", rot, reference[target]) + trans
    return x[:, anchor] + np.einsum("fij,j->fi", rot, reference[target] - reference[anchor])


def rebuild_inner_lips(positions, reference, siblings: dict, k: int = 3) -> np.ndarray:
    """Inner-lip markers as offsets in the local surface frame of their outer sibling (001 section 5.2).

    Parameters
    ----------
    positions : (n_frames, n_markers, 3)
    reference : (n_markers, 3) rest pose holding every marker (e.g. the target's labelled markers)
    siblings : dict inner index -> outer index
    k : int
        The sibling's local frame is the rigid fit of the sibling and its ``k`` nearest
        markers (excluding inner-lip markers) between the reference and each frame.

    Returns
    -------
    positions with the inner markers replaced in every frame where the frame could be built.
    """
    x = np.array(positions, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    inner = set(siblings)
    cand = np.array([i for i in range(ref.shape[0]) if i not in inner], dtype=np.intp)
    for i, o in siblings.items():
        d = np.linalg.norm(ref[cand] - ref[o], axis=1)
        local = cand[np.argsort(d)[:k + 1]]          # includes the sibling itself (distance 0)
        pred = predict_from_frame(x, ref, i, local, anchor=o)
        good = np.isfinite(pred).all(axis=1)
        x[good, i] = pred[good]
    return x


def fill_gaps(positions, reference=None, max_gap: int = 12, k: int = 4, fill_long: bool = True,
              labels=None) -> tuple[np.ndarray, GapReport]:
    """Fill gaps from the rigid motion of each marker's neighbours (001 section 5.2).

    Every gap frame gets ``R_t ref_m + t_t`` from the rigid fit of the marker's ``k``
    nearest neighbours visible in that frame; the prediction is then corrected by the
    observed-minus-predicted offset at the gap's ends, interpolated linearly across the
    gap, so the filled track meets the real one without a step. Gaps longer than
    ``max_gap`` frames are reported (``GapReport.long``) and filled only if ``fill_long``.
    Frames where fewer than 3 neighbours are visible stay NaN (``unfillable``).

    ``reference`` (n_markers, 3) is a pose holding every marker; by default the per-marker
    median over frames, which is a valid pose only once head motion has been removed
    (:func:`remove_rigid_motion` first).
    """
    x = np.array(positions, dtype=np.float64)
    nf, nm, _ = x.shape
    names = labels if labels is not None else [str(i) for i in range(nm)]
    ok = np.isfinite(x).all(axis=2)
    dead = ~ok.any(axis=0)
    if dead.all():
        raise InputError("every marker is missing in every frame: nothing to rebuild from")
    if reference is None:
        reference = np.nanmedian(np.where(ok[..., None], x, np.nan)[:, ~dead], axis=0)
        full = np.full((nm, 3), np.nan)
        full[~dead] = reference
        reference = full
    ref = np.asarray(reference, dtype=np.float64)
    nb = neighbours(ref, k)
    report = GapReport()
    for m in range(nm):
        if ok[:, m].all():
            continue
        starts, lens = _runs(~ok[:, m])
        if not np.isfinite(ref[m]).all():      # a marker never seen needs its place in ``reference``
            report.unfillable += [(names[m], int(s), int(n)) for s, n in zip(starts, lens)]
            continue
        pred = predict_from_frame(x, ref, m, nb[m])
        for s, n in zip(starts, lens):
            s, n = int(s), int(n)
            if n > max_gap:
                report.long.append((names[m], s, n))
                if not fill_long:
                    continue
            seg = pred[s:s + n]
            before = x[s - 1, m] - pred[s - 1] if s > 0 and np.isfinite(pred[s - 1]).all() else None
            after = x[s + n, m] - pred[s + n] if s + n < nf and np.isfinite(pred[s + n]).all() else None
            if before is None and after is None:
                off = np.zeros((n, 3))
            elif before is None or after is None:
                off = np.broadcast_to(before if after is None else after, (n, 3))
            else:
                a = (np.arange(1, n + 1) / (n + 1))[:, None]
                off = (1 - a) * before + a * after
            val = seg + off
            x[s:s + n, m] = val
            still = ~np.isfinite(val).all(axis=1)
            if still.any():
                r0, rl = _runs(still)
                report.unfillable += [(names[m], s + int(a0), int(b0)) for a0, b0 in zip(r0, rl)]
            if n <= max_gap:
                report.filled.append((names[m], s, n))
    return x, report
