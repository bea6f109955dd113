"""The rig's curves solved frame by frame from the head-stabilised contours.

The paper's route (section 5 of 004_119ba07521a9af0b.txt, Eqs. 2 and 4) goes through key weights; here the
rig's shapes are solved for every frame directly, one bounded, sparse least squares for all frames at once::

    min_{lo <= c_t <= hi}  sum_t ||D (A c_t + F q_t - b_t)||^2 + lambda_1 sum_t 1^T c_t
                           + lambda_s sum_t ||S c_t||^2 + mu sum_t ||c_t - c_{t-1}||^2

by projected accelerated gradient (FISTA, Beck and Teboulle 2009). :class:`RigSolver` fits it on a take and
solves other frames with the take's statistics. Design notes and figures: docs/retarget.md, "Notes on the code",
``retarget/rig/solve.py``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.retarget.rig.model import mirror_pairs
from keyshape.retarget.defaults import SolveOptions

#: Frames (spread evenly over the take) the rest's offset is estimated on: a statistic of the take's
#: relaxed state, which most frames show, so a subsample serves (and keeps the extra solve short).
OFFSET_FRAMES = 300

#: Regions whose antisymmetric motion that follows head yaw is taken out before the solve (:func:`yaw_slide`):
#: the mouth, in front of the eye corners the 2D head is stabilised on, slides sideways with yaw.
YAW_REGIONS = ("mouth",)



def _box_lsq(A: np.ndarray, B: np.ndarray, bounds: tuple[float, float] = (0.0, 1.0), l1: float = 0.0,
            Q: np.ndarray | None = None, smooth: float = 0.0, free: np.ndarray | None = None,
            offset: np.ndarray | None = None, max_iter: int = 2000, tol: float = 1e-7,
            return_offset: bool = False):
    """All frames' bounded, sparse least squares at once (projected FISTA).

    ``min_{lo <= c_t <= hi, d} sum_t ||A c_t + E d + F q_t - b_t||^2 + l1 * sum_t 1^T c_t + sum_t c_t^T Q c_t
    + smooth * sum_t ||c_t - c_{t-1}||^2``, ``E d`` (``offset``) one unknown motion shared by every frame (the
    error of the rest the targets are measured from); the two blocks take their own step (``2 L_c``, ``2 T L_d``).

    Parameters
    ----------
    A : (m, n) motion per unit of each unknown
    B : (T, m) one target per frame
    bounds : box of every unknown (``lo >= 0`` so the L1 term is linear)
    l1 : weight of the L1 term
    Q : (n, n) symmetric positive semi-definite prior (the left-right term)
    smooth : weight of the first-difference term between consecutive rows of ``B``
    free : (m, k) nuisance motions with free coefficients (eliminated exactly by projecting
        the rows onto their orthogonal complement)
    offset : (m, k) motions ``E`` of an unknown offset ``d`` shared by all frames (None: no offset)
    max_iter, tol : stop when no unknown moved more than ``tol * (hi - lo)`` in an iteration
    return_offset : also return ``d``

    Returns
    -------
    (T, n) the unknowns of every frame (and ``d`` (k,) with ``return_offset``)
    """
    A, B = np.asarray(A, float), np.atleast_2d(np.asarray(B, float))
    lo, hi = bounds
    if lo < 0 or hi <= lo:
        raise InputError(f"_box_lsq needs 0 <= lo < hi, got {bounds}")
    if A.ndim != 2 or B.shape[1] != A.shape[0]:
        raise InputError(f"_box_lsq: A {A.shape} and B {B.shape} do not match")
    n = A.shape[1]
    E = np.zeros((A.shape[0], 0)) if offset is None else np.asarray(offset, float)
    if E.shape[0] != A.shape[0]:
        raise InputError(f"_box_lsq: offset {E.shape} and A {A.shape} do not match")
    if free is not None and free.shape[1]:
        F = np.asarray(free, float)
        P = np.eye(len(F)) - F @ np.linalg.pinv(F)
        A, B, E = P @ A, B @ P, P @ E
    G = A.T @ A + (np.zeros((n, n)) if Q is None else np.asarray(Q, float))
    H = B @ A
    k = E.shape[1]
    L = 2 * (float(np.linalg.eigvalsh(G).max()) + 4 * smooth) * 1.001 + 1e-300
    if k:
        AE, EE, BE = A.T @ E, E.T @ E, B.sum(axis=0) @ E
        Le = 2 * len(B) * float(np.linalg.eigvalsh(EE).max()) * 1.001 + 1e-300
        L, Le = 2 * L, 2 * Le                       # block-diagonal bound of the joint Hessian
    C = np.full((len(B), n), float(lo))
    Y, t = C.copy(), 1.0
    d = yd = np.zeros(k)
    for _ in range(max_iter):          # iterations, each one product over all frames
        g = 2 * (Y @ G - H) + l1
        if k:
            g += 2 * (AE @ yd)[None]
        if smooth and len(Y) > 1:
            dy = np.diff(Y, axis=0)
            g[:-1] -= 2 * smooth * dy
            g[1:] += 2 * smooth * dy
        Cn = np.clip(Y - g / L, lo, hi)
        tn = (1 + np.sqrt(1 + 4 * t * t)) / 2
        step = np.abs(Cn - C).max(initial=0.0)
        if k:
            dn = yd - 2 * (Y.sum(axis=0) @ AE + len(B) * (EE @ yd) - BE) / Le
            yd = dn + ((t - 1) / tn) * (dn - d)
            d = dn
        Y = Cn + ((t - 1) / tn) * (Cn - C)
        C, t = Cn, tn
        if step < tol * (hi - lo):
            break
    return (C, d) if return_offset else C


def contour_measures(scheme, points: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The measures an animator reads of a region, as linear maps of its points' motion: each closed contour's
    opening, width and corner heights (no width or corners where the corners are rigid points), each open
    contour's end heights.

    Parameters
    ----------
    scheme : :class:`~keyshape.base.schemes.Scheme`
    points : the region's point indices

    Returns
    -------
    list of (name, (r, len(points), 2) array): each measure block, rows applied to the motion
    ``(len(points), 2)`` by ``np.einsum("rpd,pd->r", M, motion)``
    """
    loc = {int(p): i for i, p in enumerate(points)}
    out = []
    for name, pts in scheme.contours.items():
        pts = [int(p) for p in pts]
        if not pts or not all(p in loc for p in pts):
            continue
        corners = scheme.corners.get(name)
        if scheme.closed.get(name) and corners:
            i0, i1 = pts.index(corners[0]), pts.index(corners[1])
            ring = pts[i0:] + pts[:i0]
            k = (i1 - i0) % len(pts)
            upper, lower = ring[1:k], ring[k + 1:][::-1]
            pairs = list(zip(upper, lower))
            if pairs:
                M = np.zeros((len(pairs), len(points), 2))
                for r, (a, b) in enumerate(pairs):
                    M[r, loc[a], 1], M[r, loc[b], 1] = 1.0, -1.0
                out.append((f"{name} opening", M))
            if set(corners) <= set(scheme.rigid):
                continue                      # corners held still by the head stabilisation
            W = np.zeros((1, len(points), 2))
            W[0, loc[corners[1]], 0], W[0, loc[corners[0]], 0] = 1.0, -1.0
            out.append((f"{name} width", W))
            Hc = np.zeros((2, len(points), 2))
            for r, c in enumerate(corners):
                Hc[r, [loc[p] for p in pts], 1] = -1.0 / len(pts)
                Hc[r, loc[c], 1] += 1.0
            out.append((f"{name} corners", Hc))
        elif not scheme.closed.get(name) and len(pts) >= 2:
            E = np.zeros((2, len(points), 2))
            E[0, loc[pts[0]], 1] = E[1, loc[pts[-1]], 1] = 1.0
            out.append((f"{name} ends", E))
    return out


def region_rows(scheme, points: np.ndarray, motion: np.ndarray, floor: float = 0.25
                ) -> tuple[np.ndarray, list[str]]:
    """The row weighting ``D`` of a region: blocks of equal weight, each scaled by its motion.

    Blocks: each contour's points, then each of :func:`contour_measures`; a block's rows are divided by its RMS
    motion over the take (at least ``floor`` times the largest block's) and by the square root of its row count.

    Parameters
    ----------
    scheme, points : the scheme and the region's point indices
    motion : (T, len(points), 2) the actor's motion from the neutral (NaN rows ignored)

    Returns
    -------
    D : (r, len(points), 2) rows applied to a motion by ``einsum("rpd,pd->r")``
    names : block name of each row
    """
    loc = {int(p): i for i, p in enumerate(points)}
    blocks = []
    for name, pts in scheme.contours.items():
        idx = [loc[int(p)] for p in pts if int(p) in loc]
        if not idx:
            continue
        M = np.zeros((2 * len(idx), len(points), 2))
        r = np.arange(len(idx))
        M[2 * r, idx, 0] = M[2 * r + 1, idx, 1] = 1.0
        blocks.append((name, M))
    blocks += contour_measures(scheme, points)
    ok = np.isfinite(motion).all(axis=(1, 2))
    mo = motion[ok]
    rms = np.array([np.sqrt(np.mean(np.einsum("rpd,tpd->tr", M, mo) ** 2)) if len(mo) else 1.0 for _, M in blocks])
    rms = np.maximum(rms, floor * rms.max(initial=0.0) + 1e-12)
    D = np.concatenate([M / (s * np.sqrt(len(M))) for (_, M), s in zip(blocks, rms)])
    names = [n for n, M in blocks for _ in range(len(M))]
    return D, names


def _is_eye(scheme, name: str) -> bool:
    """A closed contour with corners named ``eye*`` (the lids)."""
    return name.startswith("eye") and bool(scheme.closed.get(name)) and bool(scheme.corners.get(name))


def held_rest_points(scheme) -> list[int]:
    """Points whose rest the rest's offset leaves alone: the lids (the open eye :func:`eye_calibration`
    measures closure from) and the pupils (``pupil*`` contours; straight ahead is a gaze, not an expression)."""
    from keyshape.decompose.gaze import pupil_points
    return [p for name, pts in scheme.contours.items() if _is_eye(scheme, name) for p in pts] + pupil_points(scheme)


def eye_width_motions(scheme, points: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Each eye's sideways motions, fitted freely by the solve: a horizontal stretch about the eye's centre
    and a horizontal shift (two columns per eye contour of the region), so that an eye's foreshortening
    under head yaw is not read as lid motion.

    Parameters
    ----------
    scheme : the landmark scheme (eye contours: closed, with corners, named ``eye*``)
    points : the region's point indices
    rest : (len(points), 2) the region's rest in the rig's frame

    Returns
    -------
    (len(points) * 2, k) motions flattened like the points (k = 0 where the region holds no eye)
    """
    loc = {int(p): i for i, p in enumerate(points)}
    P = np.asarray(rest, float)
    cols = []
    for name, pts in scheme.contours.items():
        if not _is_eye(scheme, name) or not all(int(p) in loc for p in pts):
            continue
        idx = [loc[int(p)] for p in pts]
        stretch, shift = np.zeros_like(P), np.zeros_like(P)
        stretch[idx, 0] = P[idx, 0] - P[idx, 0].mean()
        shift[idx, 0] = 1.0
        cols += [stretch.ravel(), shift.ravel()]
    return np.array(cols).T if cols else np.zeros((2 * len(P), 0))


def symmetric_offsets(rig_points: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Left-right symmetric heights of a region's points: the basis of the rest's offset.

    A column per mirrored pair (:func:`mirror_partners`) moves both points up alike; no sideways column.

    Parameters
    ----------
    rig_points : (n_points, 2) the rig's neutral landmark points of the region
    keep : (n_points,) bool, the points the offset may move

    Returns
    -------
    (n_points * 2, k) motions, flattened like the points
    """
    P = np.asarray(rig_points, float)
    partner = mirror_partners(P)
    keep = np.asarray(keep, bool)
    i = np.flatnonzero((partner >= np.arange(len(P))) & keep & keep[partner])      # one column per pair
    out = np.zeros((len(P), 2, len(i)))
    out[i, 1, np.arange(len(i))] = out[partner[i], 1, np.arange(len(i))] = 1.0
    return out.reshape(2 * len(P), len(i))


def rigid_frame_deltas(rig_points: np.ndarray, deltas: np.ndarray, rigid: Sequence[int],
                       keep: Sequence[int] = ()) -> np.ndarray:
    """The rig's landmark motion per shape seen in the actor's head frame: the rigid points' height held.

    Each shape's motion loses the rigid points' mean vertical motion, ``u_s - (0, mean_k u_s[rigid_k]_y)`` at every
    point (the actor's shapes are stabilised on those points, :class:`~keyshape.decompose.stabilize.RigidStabilizer`);
    the ``keep`` points (the pupils) keep their motion as given, in the skull's frame.

    Parameters
    ----------
    rig_points : (n_points, 2) the rig's neutral scheme points (:func:`~keyshape.retarget.rig.model.project`)
    deltas : (n_shapes, n_points, 2) their motion per unit of each shape
    rigid : indices of the points the actor's shapes were stabilised on (empty: ``deltas`` as given)
    keep : indices of points whose motion is left as given

    Returns
    -------
    (n_shapes, n_points, 2) a new array
    """
    U = np.array(deltas, float)
    rigid = np.asarray(list(rigid), dtype=np.intp)
    if len(rigid) == 0:
        return U
    if len(rigid) > np.asarray(rig_points).shape[0] or rigid.max() >= U.shape[1]:
        raise InputError(f"rigid points {rigid.tolist()} are not among the rig's {U.shape[1]} scheme points")
    moved = np.setdiff1d(np.arange(U.shape[1]), np.asarray(list(keep), dtype=np.intp))
    U[:, moved, 1] -= U[:, rigid, 1].mean(axis=1)[:, None]
    return U


def mirror_partners(rig_points: np.ndarray) -> np.ndarray:
    """Index of each point's left-right mirror image: the rig point nearest its reflection about the rig's
    midline (``x = 0``, rig landmark neutral, :func:`~keyshape.retarget.rig.model.project`), itself on the midline."""
    P = np.asarray(rig_points, float)
    return np.argmin((((P * [-1.0, 1.0])[:, None] - P[None]) ** 2).sum(-1), axis=1)


def yaw_slide(motion: np.ndarray, partner: np.ndarray, yaw: np.ndarray, rest_yaw: float = 0.0) -> np.ndarray:
    """The part of a region's motion that head yaw slides sideways, estimated over the take.

    To first order yaw ``theta`` moves only the antisymmetric part of the motion, ``o = (u - M u) / 2`` (``M`` the
    mirror, ``(M u)_i = (-u_x, u_y)`` of point ``i``'s partner), in proportion to ``sin(theta)``; per point and axis
    the least squares over the take

    ``o_t = a + b (sin(theta_t) - s_0) + e_t``,  ``s_0 = sin(rest_yaw)``

    gives ``b``, and ``b (sin(theta_t) - s_0)`` is returned (zero at the rest's yaw).

    Parameters
    ----------
    motion : (T, n_points, 2) the region's motion from its rest, axes of the rig (x along the eye line; no NaN)
    partner : (n_points,) index of each point's mirror image (:func:`mirror_partners`); a region
        whose points are not closed under the mirror is left alone (zeros)
    yaw : (T,) head yaw per frame (radians; any zero, e.g. :class:`~keyshape.decompose.head3d.HeadPose3D`'s)
    rest_yaw : the yaw of the frame the rest was taken from (same zero)

    Returns
    -------
    (T, n_points, 2) the slide, to subtract from ``motion`` (zeros where ``yaw`` does not vary)
    """
    U = np.asarray(motion, float)
    s = np.sin(np.asarray(yaw, float)) - np.sin(float(rest_yaw))
    if len(s) != len(U):
        raise InputError(f"yaw_slide: {len(s)} yaw values for {len(U)} frames of motion")
    b = _yaw_slope(U, np.asarray(partner, np.intp), s)
    return np.zeros_like(U) if b is None else s[:, None, None] * b[None]


def _yaw_slope(U: np.ndarray, partner: np.ndarray, s: np.ndarray) -> np.ndarray | None:
    """:func:`yaw_slide`'s slope ``b`` (n_points, 2) of each point's odd motion on ``s = sin(yaw) - sin(rest_yaw)``
    over the take (None where ``s`` does not vary or the points are not closed under the mirror)."""
    sc = s - s.mean()
    var = float(sc @ sc)
    if var <= 1e-12 * len(s) or len(partner) != U.shape[1] or (partner[partner] != np.arange(len(partner))).any():
        return None
    odd = (U - U[:, partner] * [-1.0, 1.0]) / 2
    return np.einsum("t,tpd->pd", sc, odd) / var          # slope of each point's odd motion on sin(yaw)


def yaw_stretch(shapes: np.ndarray, eye_line: np.ndarray, yaw: np.ndarray, rest_yaw: float = 0.0) -> np.ndarray:
    """The vertical stretch a 2D head stabilised on the eye corners gives a turned face, per frame and point.

    Under yaw ``theta`` the eye corners' similarity scales every height from the eye line by ``1 / cos(theta)``;
    returned is ``h (1 - cos(theta_t) / cos(theta_0))`` (``h`` each point's height from the frame's eye line,
    ``theta_0`` the rest's yaw), which brings each frame's heights to the rest's scale. No fit over the take.

    Parameters
    ----------
    shapes : (T, n_points, 2) head-frame points (image axes, y down)
    eye_line : (T,) the height of the stabilised eye corners (their mean y) in each frame
    yaw : (T,) head yaw per frame (radians); rest_yaw : the rest frame's (same zero)

    Returns
    -------
    (T, n_points, 2) the shift to subtract from ``shapes`` (zero along x)
    """
    X = np.asarray(shapes, float)
    th = np.asarray(yaw, float)
    if len(th) != len(X) or len(np.asarray(eye_line)) != len(X):
        raise InputError(f"yaw_stretch: {len(th)} yaw values and {len(np.asarray(eye_line))} eye lines for "
                         f"{len(X)} frames")
    out = np.zeros_like(X)
    k = 1.0 - np.cos(th) / np.cos(float(rest_yaw))
    out[..., 1] = (X[..., 1] - np.asarray(eye_line, float)[:, None]) * k[:, None]
    return out


def eye_calibration(scheme, points: np.ndarray, rest: np.ndarray, motion: np.ndarray, rig_rest: np.ndarray,
                    frames: int = 3, blink_closure: tuple[float, float] = (0.4, 0.6), max_scale: float = 2.5,
                    report: list | None = None) -> np.ndarray:
    """Per-point scale of the actor's motion so that the take's deepest closure of each eye closes the rig's.

    For each eye contour: the actor's opening ``g_t`` (at rest ``g_0``), the rig's neutral opening ``r_0``, the
    take's deepest closure ``k = 1 - g_min / g_0`` (``g_min`` the ``frames``-th smallest opening). A closure of
    at least ``blink_closure[1]`` is a blink read short: the eye's points' motion is scaled by ``r_0 / (k g_0)``
    (at most ``max_scale``), so that it shuts the rig's eye. One of at most ``blink_closure[0]`` is no blink (a
    squint, a partial blink): the scale is ``r_0 / g_0``, the eye's size only. Between the two the closure may
    be either, and the scale is ``r_0 / (d g_0)`` with ``d = 1 - w + w k``, ``w`` the closure's place in the
    range (0 to 1): the rig's closure at that frame, ``k / d``, rises continuously from ``k`` to shut, so a take
    whose closure reads a little deeper or shallower moves the rig's eye a little, not between half shut and shut.

    Parameters
    ----------
    scheme, points : the scheme and the region's point indices
    rest : (len(points), 2) the actor's neutral, in the rig's frame and units
    motion : (T, len(points), 2) the actor's motion from ``rest`` (rig frame)
    rig_rest : (len(points), 2) the rig's neutral points
    frames : the deepest closure is the ``frames``-th deepest frame's
    blink_closure : closures (fractions of the opening) up to which a take has no blink, and from which it has one
    max_scale : largest scale
    report : a list that receives one :class:`EyeCalibration` per eye calibrated

    Returns
    -------
    (len(points),) scale per point (1 outside the eyes)
    """
    scale = np.ones(len(points))
    loc = {int(p): i for i, p in enumerate(points)}
    ok = np.isfinite(motion).all(axis=(1, 2))
    for name, M in contour_measures(scheme, points):
        if not (name.startswith("eye") and name.endswith(" opening")) or not ok.any():
            continue
        sign = np.sign(np.einsum("rpd,pd->r", M, rest).mean())
        g0 = float(sign * np.einsum("rpd,pd->r", M, rest).mean())
        r0 = float(sign * np.einsum("rpd,pd->r", M, rig_rest).mean())
        if g0 < 1e-12 or r0 <= 0:
            continue
        g = sign * np.einsum("rpd,tpd->tr", M, motion[ok]).mean(axis=1) + g0
        deepest = 1 - float(np.sort(g)[min(frames, len(g)) - 1]) / g0
        lo, hi = blink_closure
        w = min(max((deepest - lo) / (hi - lo), 0.0), 1.0)
        k = min(r0 / g0 / (1.0 - w + w * deepest), max_scale)
        contour = [loc[int(p)] for p in scheme.contours[name[: -len(" opening")]] if int(p) in loc]
        scale[contour] = k
        if report is not None:
            report.append(EyeCalibration(name[: -len(" opening")], deepest, k, w, k >= max_scale, r0 / g0))
    return scale


@dataclass(frozen=True)
class EyeCalibration:
    """How :func:`eye_calibration` scaled one eye: ``contour`` (the scheme's name, image-left or -right), the
    take's ``deepest`` closure (fraction of the open lid gap), the ``scale`` of the lids' motion, how far that
    closure counted as a ``blink`` (1: it shuts the rig's eye; 0: the eye is only sized to the rig's, ``size``;
    between: it closes the rig's eye to ``closed``), and whether the scale hit its ``capped`` maximum (the rig's
    lids then do not quite meet at the deepest closure)."""

    contour: str
    deepest: float
    scale: float
    blink: float
    capped: bool
    size: float

    @property
    def closed(self) -> float:
        """The rig's closure at the take's deepest closure (1: shut)."""
        return self.deepest * self.scale / self.size

    def describe(self) -> str:
        """One line an animator reads."""
        side = self.contour.rsplit("_", 1)[-1]
        eye = (f"the image-{side} eye (the actor's {'right' if side == 'left' else 'left'})"
               if side in ("left", "right") else self.contour)
        if not self.blink:
            return (f"{eye}: no blink in the take (deepest closure {self.deepest:.2f} of the open lid), "
                    f"the lids keep their tracked travel at the rig's eye size")
        travel = f"lid travel x{self.scale / self.size:.2f} over the rig's eye size"
        if self.blink < 1:
            return (f"{eye}: the take's deepest closure, {self.deepest:.2f} of the open lid, may be a blink read "
                    f"short or a partial one: it closes the rig's eye to {self.closed:.2f} ({travel})")
        tail = ", the most it may: the rig's lids do not quite meet there" if self.capped else ""
        return (f"{eye}: the take's deepest closure, {self.deepest:.2f} of the open lid, closes the rig's "
                f"eye ({travel}{tail})")


def brow_calibration(scheme, points: np.ndarray, A: np.ndarray, motion: np.ndarray, curves: np.ndarray,
                     pairs: Sequence[tuple[int, int]] = (), max_scale: float = 2.0, min_r2: float = 0.5) -> np.ndarray:
    """Per-shape scale of the solved curves so that each brow end rises as far as the actor's.

    For each brow end ``e``, the actor's end height ``m_e`` and the fit's, split into the end's own shapes' part
    ``f_e`` and the others' ``o_e``, give the least-squares gain over the take (means removed)

    ``g = sum_e sum_t (m_et - o_et) f_et / sum_e sum_t f_et^2``

    pooled over an end and its mirror (``pairs``). A shape belongs to the end it moves most on the brow whose
    points it moves most; other shapes keep scale 1, and so do an end's where ``f`` explains less than ``min_r2``.

    Parameters
    ----------
    scheme, points : the scheme and the region's point indices
    A : (n_shapes, len(points), 2) the rig's motion per unit of each of the region's shapes (rig frame)
    motion : (T, len(points), 2) the actor's motion from the rest (rig frame, no NaN)
    curves : (T, n_shapes) the solved curves of the region's shapes
    pairs : mirrored shape pairs (indices into ``A``, :func:`mirror_pairs`)
    max_scale : scales kept within ``[1 / max_scale, max_scale]``
    min_r2 : least squared correlation of ``f`` with ``m - o`` (pooled) for a scale other than 1

    Returns
    -------
    (n_shapes,) scale per shape
    """
    scale = np.ones(len(A))
    if not len(A) or len(motion) < 2:
        return scale
    loc = {int(p): i for i, p in enumerate(points)}
    top = np.argmax(np.linalg.norm(A, axis=-1), axis=1)                  # each shape's most moved point
    ends = []                                                            # (own shapes, cov, var f, var m - o)
    for name, M in contour_measures(scheme, points):
        if not name.endswith(" ends"):
            continue
        contour = [loc[int(p)] for p in scheme.contours[name[: -len(" ends")]]]
        Ae = np.einsum("rpd,spd->sr", M, A)                              # (n_shapes, 2) end motion per unit
        mine = np.isin(top, contour)
        nearest = np.argmax(np.abs(Ae), axis=1)
        m = np.einsum("rpd,tpd->tr", M, motion)
        for e in range(Ae.shape[1]):
            own = mine & (nearest == e)
            if not own.any():
                continue
            f = curves[:, own] @ Ae[own, e]
            rest = m[:, e] - curves[:, ~own] @ Ae[~own, e]
            f, rest = f - f.mean(), rest - rest.mean()
            ends.append((own, float(rest @ f), float(f @ f), float(rest @ rest)))
    mirror = {i: j for a, b in pairs for i, j in ((a, b), (b, a))}
    for own, *_ in ends:
        group = [(o, c, v, w) for o, c, v, w in ends
                 if (o & own).any() or any(o[mirror[s]] for s in np.flatnonzero(own) if s in mirror)]
        cov, var, var_m = (sum(x[k] for x in group) for k in (1, 2, 3))
        if var > 1e-12 and cov * cov >= min_r2 * var * var_m:
            scale[own] = np.clip(cov / var, 1.0 / max_scale, max_scale)
    return scale


@dataclass(frozen=True)
class _RegionSystem:
    """One region's weighted system (:func:`_box_lsq` on the rows ``D``, :func:`region_rows`), fitted on a take: what
    :meth:`solve` needs to solve any frames alike (the L1 weight is scaled by the take's motion, the rest's offset
    solved on the take).

    :meth:`fit`'s ``A`` (n_shapes, n_points, 2) is the rig's projected motion per unit of each of the region's
    shapes, ``motion`` (T, n_points, 2) the actor's from the neutral in the rig's frame (no NaN); ``priors``:
    ``(sparsity, symmetry, smooth)``, dimensionless: the L1 weight times the rows' typical size, the weight of
    ``||c_L - c_R||^2`` for each mirrored pair of ``pairs`` and the temporal smoothness times the mean squared
    column norm of the weighted ``A``; ``free`` (n_points * 2, k) nuisance motions and ``rest_offset``
    (n_points * 2, k) the motions of an unknown offset of the rest shared by every frame (:func:`_box_lsq`'s
    ``offset``), flattened like the points."""

    Aw: np.ndarray
    Fw: np.ndarray | None
    Q: np.ndarray | None
    l1: float
    smooth: float
    shift: np.ndarray | None          # the rest offset's motion in the weighted rows, subtracted from every frame's
    bounds: tuple[float, float]

    @classmethod
    def fit(cls, A, motion, D, bounds, priors, pairs, free, rest_offset) -> "_RegionSystem":
        sparsity, symmetry, smooth = priors
        n = len(A)
        Aw = np.einsum("rpd,spd->rs", D, A)
        Bw = np.einsum("rpd,tpd->tr", D, motion)
        Fw = None if free is None else np.einsum("rpd,pdk->rk", D, free.reshape(len(D[0]), 2, -1))
        col = float(np.mean((Aw ** 2).sum(axis=0))) or 1.0
        Q = None
        if pairs and symmetry > 0:
            from keyshape.retarget.rig.poses import mirror_differences
            S = mirror_differences(pairs, n)
            Q = symmetry * col * S.T @ S
        l1 = sparsity * np.sqrt(col) * float(np.sqrt(np.mean((Bw ** 2).sum(axis=1))))
        shift = None
        if rest_offset is not None and rest_offset.shape[1]:
            # the rest's offset under the box and the L1 term alone (with the left-right prior a constant
            # of the weaker side would buy symmetry), then the curves from the corrected rest
            E = D.reshape(len(D), -1) @ rest_offset
            some = np.unique(np.linspace(0, len(Bw) - 1, min(len(Bw), OFFSET_FRAMES)).astype(np.intp))
            _, d = _box_lsq(Aw, Bw[some], bounds, l1, None, 0.0, Fw, E, return_offset=True)
            shift = E @ d
        return cls(Aw, Fw, Q, l1, smooth * col, shift, bounds)

    def solve(self, Bw: np.ndarray) -> np.ndarray:
        """The curves of the weighted motions ``Bw`` (T, r)."""
        if self.shift is not None:
            Bw = Bw - self.shift
        return _box_lsq(self.Aw, Bw, self.bounds, self.l1, self.Q, self.smooth, self.Fw)


@dataclass(frozen=True)
class RigLandmarks:
    """The rig as the solve sees it: its projected scheme points and their motion per shape.

    Attributes
    ----------
    neutral, deltas : the rig's projected scheme points (n_points, 2) and their motion per shape
        (n_shapes, n_points, 2) (:func:`~keyshape.retarget.rig.model.project`)
    region_shapes : {region: indices of the rig shapes it drives} (:func:`~keyshape.retarget.rig.model.shape_regions`)
    names : the rig's shape names (mirrored pairs for the left-right prior)
    bounds : the curves' range
    """

    neutral: np.ndarray
    deltas: np.ndarray
    region_shapes: Mapping[str, np.ndarray]
    names: Sequence[str]
    bounds: tuple[float, float] = (0.0, 1.0)


@dataclass(frozen=True)
class HeadParallax:
    """What a 2D head stabilisation leaves in the shapes, for :class:`RigSolver` to take out.

    Attributes
    ----------
    yaw, rest_yaw : (T,) the head's yaw per frame and at the rest's frame (radians, from the 3D head,
        :class:`~keyshape.decompose.head3d.HeadPose3D`): with :class:`SolveOptions`' ``yaw_slide`` the antisymmetric
        motion of the ``regions`` that follows yaw over the take (:func:`yaw_slide`) and with ``yaw_stretch`` the
        vertical stretch of the turn (:func:`yaw_stretch`, needs ``rigid``) are taken out; None: none taken out
        (shapes already frontalised, or no 3D head)
    rigid : the points the actor's shapes were stabilised on (a :class:`~keyshape.decompose.stabilize.RigidStabilizer`'s):
        the rig's landmark motion is taken in the same frame (:func:`rigid_frame_deltas`; the pupils' in the
        skull's); empty: as given
    regions : the regions the yaw corrections apply to
    eye_width : each eye's horizontal stretch and shift fitted freely (:func:`eye_width_motions`): the
        foreshortening of each eye under head yaw is not read as lid motion
    """

    yaw: np.ndarray | None = None
    rest_yaw: float = 0.0
    rigid: Sequence[int] = ()
    regions: Sequence[str] = YAW_REGIONS
    eye_width: bool = True


@dataclass
class _RegionFit:
    """One region's statistics of the take (:class:`RigSolver`)."""

    name: str
    idx: np.ndarray
    sh: np.ndarray
    rest: np.ndarray
    slope: np.ndarray | None           # the yaw slide's (yaw_slide)
    scale: np.ndarray | None           # each point's (eye_calibration)
    D: np.ndarray
    system: _RegionSystem
    gain: np.ndarray | None            # each shape's (brow_calibration)


class RigSolver:
    """The rig's curves of every frame straight from the head-stabilised contours, fitted once on a take and then
    applied to any frame.

    :meth:`fit` solves the take's curves (``curves_``) and keeps the take's statistics (similarity, row weights,
    yaw slopes, calibrations, L1 weight, rest offset); :meth:`transform` solves new frames with them (``smooth``
    is not applied there).

    Parameters
    ----------
    scheme : the landmark scheme (contours for :func:`region_rows`)
    rig : the rig's projected landmarks and shapes (:class:`RigLandmarks`)
    options : the solve's priors and calibrations (:class:`~keyshape.retarget.defaults.SolveOptions`: ``sparsity``,
        ``symmetry``, ``smooth`` as :class:`_RegionSystem`; ``calibrate``: each eye's lid motion scaled by
        :func:`eye_calibration`, the brow shapes' curves by :func:`brow_calibration`; ``rest_offset``: an offset
        of the actor's rest shared by every frame solved with the curves, each region's points but the lids',
        whose rest is the open eye that :func:`eye_calibration` measures; ``yaw_slide``, ``yaw_stretch``: with
        the head's yaw)
    nuisance : {region: "none" | "translation" | "similarity"} (default: a free translation of the
        mouth, :func:`~keyshape.retarget.rig.poses.auto_nuisance` for stabilised heads)
    """

    def __init__(self, scheme, rig: RigLandmarks, options: SolveOptions = SolveOptions(),
                 nuisance: Mapping[str, str] | None = None):
        self.scheme, self.rig, self.options, self.nuisance = scheme, rig, options, nuisance

    def fit(self, shapes: np.ndarray, regions: Mapping[str, tuple[np.ndarray, np.ndarray]],
            head: HeadParallax = HeadParallax(), fixed: np.ndarray | None = None,
            report: dict | None = None) -> "RigSolver":
        """Solve the take ``shapes``: sets ``curves_`` (T, n_shapes), within the rig's bounds (shapes of no region
        stay at the lower bound), and the take's statistics.

        Parameters
        ----------
        shapes : (T, n_points, 2) head-frame shapes (:func:`~keyshape.decompose.regions.head_shapes`;
            NaN rows: failed frames, whose curves are interpolated linearly in time)
        regions : {region: (point indices, the actor's neutral of those points)}
        head : the head's parallax to take out (:class:`HeadParallax`)
        fixed : (T, n_shapes) curves known beforehand (gaze's ``eyeLook*``, which move ICT-FaceKit's lids):
            their landmark motion is taken from the actor's before the solve, and they are kept in
            the result where non-zero (the solved shapes are the others)
        report : a dict that receives what the calibrations did: ``"eyes"`` a list of :class:`EyeCalibration`,
            ``"brows"`` {shape name: scale of its curve} for the shapes :func:`brow_calibration` scaled
        """
        from keyshape.base.geometry import fit_similarity
        from keyshape.retarget.rig.poses import auto_nuisance, nuisance_motions
        scheme, rig, o = self.scheme, self.rig, self.options
        landmark_neutral, region_shapes, shape_names, bounds = rig.neutral, rig.region_shapes, rig.names, rig.bounds
        yaw, rest_yaw, rigid, yaw_regions = head.yaw, head.rest_yaw, head.rigid, head.regions
        X = np.asarray(shapes, float)
        ok = np.isfinite(X.reshape(len(X), -1)).all(axis=1)
        if not ok.any():
            raise InputError("no successful frame to solve the rig's curves from")
        pts = np.concatenate([p for p, _ in regions.values()])
        src = np.concatenate([r for _, r in regions.values()])
        self.similarity_ = Msim = fit_similarity(src, landmark_neutral[pts])[:, :2]      # s R
        from keyshape.decompose.gaze import pupil_points
        self.deltas_ = landmark_deltas = rigid_frame_deltas(landmark_neutral, rig.deltas, rigid,
                                                            keep=pupil_points(scheme))
        self.head_, self.regions_ = head, []
        out = np.full((len(X), len(shape_names)), float(bounds[0]))
        held = held_rest_points(scheme)
        for region, (idx, rest) in regions.items():
            sh = np.asarray(region_shapes.get(region, []), dtype=np.intp)
            if not len(sh):
                continue
            idx = np.asarray(idx)
            rest_r = np.asarray(rest, float) @ Msim.T
            motion = self._motion(X, ok, idx, np.asarray(rest, float), region, yaw, fixed)
            if fixed is not None:
                sh = sh[np.abs(np.asarray(fixed, float)[ok][:, sh]).max(axis=0, initial=0.0) == 0]
            slope = None
            if yaw is not None and o.yaw_slide and region in yaw_regions:
                sy = np.sin(np.asarray(yaw, float)[ok]) - np.sin(float(rest_yaw))
                slope = _yaw_slope(motion, mirror_partners(landmark_neutral[idx]), sy)
                if slope is not None:
                    motion = motion - sy[:, None, None] * slope[None]
            scale = None
            if o.calibrate:
                scale = eye_calibration(scheme, idx, rest_r, motion, landmark_neutral[idx],
                                        report=None if report is None else report.setdefault("eyes", []))
                motion = motion * scale[None, :, None]
            D, _ = region_rows(scheme, idx, motion)
            kind = (self.nuisance or {}).get(region) or auto_nuisance(region, True)
            F = nuisance_motions(rest_r, kind)
            if head.eye_width:
                Fe = eye_width_motions(scheme, idx, rest_r)
                F = Fe if F is None else np.concatenate([F, Fe], axis=1)
            names = [shape_names[j] for j in sh]
            A = landmark_deltas[sh][:, idx]
            system = None
            if len(A):
                system = _RegionSystem.fit(A, motion, D, bounds, (o.sparsity, o.symmetry, o.smooth), mirror_pairs(names),
                                           F, symmetric_offsets(landmark_neutral[idx], ~np.isin(idx, held))
                                           if o.rest_offset else None)
                c = system.solve(np.einsum("rpd,tpd->tr", D, motion))
            else:
                c = np.zeros((len(motion), 0))
            gain = None
            if o.calibrate:
                gain = brow_calibration(scheme, idx, A, motion, c, mirror_pairs(names))
                c = np.clip(c * gain[None], *bounds)
                if report is not None:
                    report.setdefault("brows", {}).update({names[j]: float(gain[j]) for j in np.flatnonzero(gain != 1.0)})
            if system is not None:
                self.regions_.append(_RegionFit(region, idx, sh, np.asarray(rest, float), slope, scale, D, system, gain))
            full = np.empty((len(X), len(sh)))
            full[ok] = c
            if not ok.all():
                t = np.arange(len(X))
                for j in range(len(sh)):          # loop over shapes, not frames
                    full[~ok, j] = np.interp(t[~ok], t[ok], c[:, j])
            out[:, sh] = full
        self.curves_ = _with_fixed(out, fixed)
        return self

    def _motion(self, X: np.ndarray, ok: np.ndarray, idx: np.ndarray, rest: np.ndarray, region: str, yaw, fixed):
        """The ``ok`` frames' motion of a region's points ``idx`` from ``rest`` in the rig's frame: the turn's
        vertical stretch (:func:`yaw_stretch`) and the ``fixed`` curves' landmark motion taken out."""
        head, Xr = self.head_, X[ok][:, idx]
        if head.yaw is not None and self.options.yaw_stretch and len(head.rigid) and region in head.regions:
            Xr = Xr - yaw_stretch(Xr, X[ok][:, list(head.rigid), 1].mean(axis=1), np.asarray(yaw, float)[ok],
                                  head.rest_yaw)
        motion = (Xr - rest) @ self.similarity_.T
        if fixed is not None:
            motion = motion - np.einsum("ts,spd->tpd", np.asarray(fixed, float)[ok], self.deltas_[:, idx])
        return motion

    def transform(self, shapes: np.ndarray, yaw: np.ndarray | None = None,
                  fixed: np.ndarray | None = None) -> np.ndarray:
        """The curves (T, n_shapes) of new frames ``shapes`` (T, n_points, 2) with the fitted take's statistics.

        ``yaw`` : (T,) the frames' head yaw (as :class:`HeadParallax`'s, the same zero; needed
        where the fit took them out); ``fixed`` : (T, n_shapes) curves known beforehand (the gaze shapes'). Frames
        with a NaN point get the curves' lower bound.
        """
        if not hasattr(self, "curves_"):
            from keyshape.base.errors import NotFittedError
            raise NotFittedError("RigSolver.transform before fit")
        o, head, bounds = self.options, self.head_, self.rig.bounds
        X = np.asarray(shapes, float)
        ok = np.isfinite(X.reshape(len(X), -1)).all(axis=1)
        out = np.full((len(X), len(self.rig.names)), float(bounds[0]))
        if yaw is None and head.yaw is not None and (o.yaw_slide or o.yaw_stretch):
            raise InputError("RigSolver.transform: the solver was fitted with the head's yaw; give the frames'")
        for f in self.regions_:
            motion = self._motion(X, ok, f.idx, f.rest, f.name, yaw, fixed)
            if f.slope is not None:
                sy = np.sin(np.asarray(yaw, float)[ok]) - np.sin(float(head.rest_yaw))
                motion = motion - sy[:, None, None] * f.slope[None]
            if f.scale is not None:
                motion = motion * f.scale[None, :, None]
            c = f.system.solve(np.einsum("rpd,tpd->tr", f.D, motion))
            if f.gain is not None:
                c = np.clip(c * f.gain[None], *bounds)
            full = np.full((len(X), len(f.sh)), float(bounds[0]))
            full[ok] = c
            out[:, f.sh] = full
        return _with_fixed(out, fixed)


def _with_fixed(curves: np.ndarray, fixed: np.ndarray | None) -> np.ndarray:
    """``curves`` with the ``fixed`` curves (the gaze shapes') where those are not 0 throughout."""
    if fixed is not None:
        live = np.abs(np.asarray(fixed, float)).max(axis=0, initial=0.0) > 0
        curves[:, live] = np.asarray(fixed, float)[:, live]
    return curves


def pose_override(curves: np.ndarray, frames: np.ndarray, weights: np.ndarray, columns: Sequence[str],
                  library: Mapping, shape_names: Sequence[str], key_frames: Mapping[str, int],
                  source=None) -> np.ndarray:
    """The artist's pose library over the solved curves: ``c_t + sum_i w_ti (p_i - c(f_i))``.

    Each key ``i`` of the library (POSES.json, corrected by hand in ``keyshape pose-edit``) says
    what the rig shows at its frame ``f_i``; the solve's own curves there ``c(f_i)`` are replaced by
    the pose ``p_i``, and every frame moves by the same correction in proportion to its weight of
    the key (the paper's Eq. 2 applied to the corrections, ``w`` the key weights of
    ``keyshape decompose``). Only the shapes of each key's region are touched.

    Parameters
    ----------
    curves : (T, n_shapes) solved curves (:class:`RigSolver`) of the frames ``frames``
    weights : (T, n_keys) key weights of the same frames, columns ``columns``
    library : POSES.json dict (``regions`` -> ``shapes``, ``keys``), ``range``
    shape_names : the rig's shape names
    key_frames : {key name: its frame}

    Returns
    -------
    (T, n_shapes) within the library's range
    """
    from keyshape.retarget.rig.poses import pose_vector
    index = {n: j for j, n in enumerate(shape_names)}
    row = {int(f): i for i, f in enumerate(frames)}
    col = {c: i for i, c in enumerate(columns)}
    out = np.array(curves, float)
    lo, hi = library.get("range", (0.0, 1.0))
    for reg in library["regions"].values():
        shapes = [index[s] for s in reg["shapes"]]
        for key, pose in reg["keys"].items():
            if key not in col:
                raise InputError(f"key {key!r} of the pose library has no weight column", source)
            if key not in key_frames or key_frames[key] not in row:
                raise InputError(f"key {key!r} of the pose library is not a frame of these tracks", source)
            delta = pose_vector(pose, reg["shapes"]) - np.asarray(curves, float)[row[key_frames[key]], shapes]
            out[:, shapes] += np.asarray(weights, float)[:, [col[key]]] * delta[None]
    return np.clip(out, lo, hi)
