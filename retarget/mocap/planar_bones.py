"""Planar-bone deformation of a dense mesh by a triangulated control surface (section 4 of 001_7296bf6ea73cabea.txt).

Each vertex is bound to the bones' regions (eqs. (3)-(6)) and frames (eqs. (1), (2), (7)-(8)) once, deformed per
frame by eqs. (9)-(10) and blended with eqs. (11)-(12); masks (section 4.3) forbid bones to move vertices.
Design notes and figures: docs/mocap.md, "Notes on the code", ``retarget/mocap/planar_bones.py``.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.spatial import cKDTree

from keyshape.base.errors import InputError, NotFittedError

try:  # out += A @ X for a CSC A, in place (scipy's own kernel behind ``A @ X``; no temporary)
    from scipy.sparse._sparsetools import csc_matvecs as _csc_matvecs
except ImportError:  # pragma: no cover - a scipy without it: the public product below
    _csc_matvecs = None

#: frames whose wedge pairs (eq. 10) deform_many evaluates in one pass over the pairs
_WEDGE_FRAMES = 8
N_SLOTS = 7  # per bone: A, B_0, B_1, B_2, C_0, C_1, C_2
REGION_NAMES = ("A", "B0", "B1", "B2", "C0", "C1", "C2")


def _unit(v: np.ndarray, eps: float = 1e-300) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, eps)


def bone_frames(corners: np.ndarray) -> np.ndarray:
    """Origins and frame rows of the 7 region slots of every bone.

    Parameters
    ----------
    corners : (..., n_bones, 3, 3) triangle corners ``V_0, V_1, V_2``

    Returns
    -------
    (..., n_bones, 7, 4, 3): for slot ``A, B_0..2, C_0..2`` the origin then rows 1-3
    (eqs. 2, 7, 8).
    """
    v0, v1, v2 = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    e = np.stack([v1 - v0, v2 - v1, v0 - v2], axis=-2)          # (..., nb, 3, 3) eq. (6)
    n = _unit(np.cross(e[..., 0, :], v2 - v0))                   # eq. (2)
    m = _unit(np.cross(e, n[..., None, :]))                      # outward edge normals, eq. (7)
    nn = np.broadcast_to(n[..., None, :], e.shape)
    out = np.empty(corners.shape[:-2] + (N_SLOTS, 4, 3))
    out[..., 0, 0, :] = v0
    out[..., 0, 1, :] = e[..., 0, :]
    out[..., 0, 2, :] = v2 - v0
    out[..., 0, 3, :] = n
    out[..., 1:4, 0, :] = corners
    out[..., 1:4, 1, :] = e
    out[..., 1:4, 2, :] = m
    out[..., 1:4, 3, :] = nn
    out[..., 4:7, 0, :] = corners
    out[..., 4:7, 1, :] = m
    out[..., 4:7, 2, :] = np.roll(m, 1, axis=-2)                 # m_{i-1}
    out[..., 4:7, 3, :] = nn
    return out


def closest_feature(points: np.ndarray, corners: np.ndarray):
    """Nearest feature of a triangle to each point (the partition of eqs. 3-5).

    Parameters
    ----------
    points : (n, 3)
    corners : (n, 3, 3) the triangle of each point

    Returns
    -------
    region : (n,) int in 0..6 (``A, B_0, B_1, B_2, C_0, C_1, C_2``)
    distance : (n,) ``|S - closest point on the triangle|`` (``d_ij`` of eq. 12)
    """
    v0 = corners[:, 0]
    e1 = corners[:, 1] - v0
    e2 = corners[:, 2] - v0
    rel = points - v0
    # barycentric coordinates (u along e1, v along e2) of the projection
    g11 = np.einsum("ij,ij->i", e1, e1)
    g12 = np.einsum("ij,ij->i", e1, e2)
    g22 = np.einsum("ij,ij->i", e2, e2)
    b1 = np.einsum("ij,ij->i", rel, e1)
    b2 = np.einsum("ij,ij->i", rel, e2)
    det = g11 * g22 - g12 * g12
    u = (g22 * b1 - g12 * b2) / det
    v = (g11 * b2 - g12 * b1) / det
    inside = (u >= 0) & (v >= 0) & (u + v <= 1)
    proj = v0 + u[:, None] * e1 + v[:, None] * e2
    normal_dist = np.linalg.norm(points - proj, axis=1)
    # distance to each edge segment i (V_i -> V_{i+1}) with its clamped parameter
    starts = corners
    edges = np.roll(corners, -1, axis=1) - corners
    t = np.einsum("nij,nij->ni", points[:, None, :] - starts, edges) / np.einsum("nij,nij->ni", edges, edges)
    tc = np.clip(t, 0.0, 1.0)
    near = starts + tc[..., None] * edges
    dist = np.linalg.norm(points[:, None, :] - near, axis=2)
    k = np.argmin(dist, axis=1)
    rows = np.arange(len(points))
    tk = tc[rows, k]
    region = np.where(tk <= 0.0, 4 + k, np.where(tk >= 1.0, 4 + (k + 1) % 3, 1 + k))
    region = np.where(inside, 0, region)
    distance = np.where(inside, normal_dist, dist[rows, k])
    return region.astype(np.intp), distance


class PlanarBones:
    """A mesh bound to a planar-bone control surface (eqs. 1-12 of 001).

    ``PlanarBones(radius_scale, unbound).fit(mesh_vertices, control_points, triangles, masks)``
    binds the mesh once; :meth:`deform` then moves it with the control points. See the
    module docstring for the maths and :meth:`fit` for the parameters.

    Attributes
    ----------
    n_vertices_, n_bones_, n_controls_ : int
    triangles_ : (n_bones, 3) int control-point indices of every bone
    radii_ : (n_bones,) affection radius ``R_j`` (eq. 12)
    pair_vertex_, pair_bone_, pair_region_ : (n_pairs,) one row per (vertex, bone) binding;
        the region is an index into ``REGION_NAMES`` (A, B0, B1, B2, C0, C1, C2)
    pair_weight_ : (n_pairs,) normalised weights (sum to one per bound vertex)
    pair_coords_ : (n_pairs, 3) local coordinates ``c`` in the region frame
    bound_ : (n_vertices,) bool, False for unbound vertices
    rest_weight_ : (n_vertices,) weight of the rest position (1 unbound, 0 fully bound)
    """

    def __init__(self, radius_scale: float = 1.0, unbound: str = "still", labels=None,
                 min_angle_deg: float = 1.0, threads: bool = True, dtype="float64"):
        self.threads = threads
        self.dtype = dtype
        self.radius_scale = radius_scale
        self.unbound = unbound
        self.labels = labels
        self.min_angle_deg = min_angle_deg

    # ------------------------------------------------------------------------------------------
    def fit(self, mesh_vertices, control_points, triangles, masks=None) -> "PlanarBones":
        """Bind every mesh vertex to the bones whose affection volume holds it.

        Parameters
        ----------
        mesh_vertices : (n_vertices, 3) rest mesh
        control_points : (n_controls, 3) rest control surface (retargeted neutral markers)
        triangles : (n_bones, 3) int, control-point indices of each bone
        masks : (n_vertices, n_bones) bool array or sparse matrix, optional
            ``False`` where bone ``j`` may not move vertex ``v`` (section 4.3).

        Parameters of the constructor
        -----------------------------
        radius_scale : float
            ``R_j`` as a multiple of the shortest control edge touching bone ``j``.
        unbound : {"still", "nearest", "fade"}
            What a vertex that no allowed bone reaches does: stay at rest, follow its nearest
            allowed bone, or (``fade``) weights are normalised only where their sum exceeds
            one and the rest position takes the remainder, so the mesh fades continuously
            to still at the edge of the control surface (normalising hard makes a step there).
        labels : sequence of str, optional
            Control-point names for error messages.
        min_angle_deg : float
            Bones with a smaller corner angle are degenerate (collinear) and refused.
        threads : bool
            Use a helper thread for :meth:`deform`/:meth:`deform_many` where there is a second core.
        dtype : {"float64", "float32"}
            Precision of the bound matrices and of the output (float32 halves the memory).

        Raises
        ------
        InputError
            Bad shapes, NaNs, indices out of range, degenerate (collinear) bones, bad masks.
        """
        radius_scale, unbound, labels, min_angle_deg = self.radius_scale, self.unbound, self.labels, self.min_angle_deg
        x = np.asarray(mesh_vertices, dtype=np.float64)
        c = np.asarray(control_points, dtype=np.float64)
        tri = np.asarray(triangles)
        if x.ndim != 2 or x.shape[1] != 3:
            raise InputError(f"`mesh_vertices`: expected shape (n_vertices, 3), got {x.shape}")
        if c.ndim != 2 or c.shape[1] != 3:
            raise InputError(f"`control_points`: expected shape (n_controls, 3), got {c.shape}")
        if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0 or not np.issubdtype(tri.dtype, np.integer):
            raise InputError(f"`triangles`: expected a non-empty int array (n_bones, 3), got {tri.dtype} {tri.shape}")
        if tri.min() < 0 or tri.max() >= len(c):
            raise InputError(f"`triangles`: indices must lie in [0, {len(c)}), found {tri.min()}..{tri.max()}")
        if not np.all(np.isfinite(x)) or not np.all(np.isfinite(c)):
            raise InputError("`mesh_vertices`/`control_points`: NaN or infinite coordinates")
        if unbound not in ("still", "nearest", "fade"):
            raise InputError(f"unbound: expected 'still', 'nearest' or 'fade', got {unbound!r}")
        dt = np.dtype(self.dtype)
        if dt not in (np.float32, np.float64):
            raise InputError(f"dtype: expected 'float64' or 'float32', got {self.dtype!r}")
        name = (lambda k: repr(labels[k])) if labels is not None else str
        corners = c[tri]
        ang = triangle_min_angles(corners)
        bad = np.flatnonzero(ang < np.deg2rad(min_angle_deg))
        if len(bad):
            j = bad[0]
            raise InputError(
                f"`triangles`: {len(bad)} degenerate (near-collinear) bone(s), e.g. bone {j} with corners "
                f"{', '.join(name(k) for k in tri[j])} (smallest angle {np.rad2deg(ang[j]):.2g} deg < {min_angle_deg}); "
                "drop them (retarget.mocap.triangulate does) or move the markers")
        nb, nv = len(tri), len(x)
        if masks is not None:
            masks = sp.csr_matrix(masks, dtype=bool) if sp.issparse(masks) else np.asarray(masks, dtype=bool)
            if masks.shape != (nv, nb):
                raise InputError(f"`masks`: expected shape (n_vertices, n_bones) = {(nv, nb)}, got {masks.shape}")

        # radii: fraction of the shortest control edge touching the bone's corners (eq. 12)
        edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        elen = np.linalg.norm(c[edges[:, 0]] - c[edges[:, 1]], axis=1)
        shortest = np.full(len(c), np.inf)
        np.minimum.at(shortest, edges[:, 0], elen)
        np.minimum.at(shortest, edges[:, 1], elen)
        radii = radius_scale * shortest[tri].min(axis=1)

        # candidate pairs: vertices within (circumscribing ball + R_j) of each bone
        centre = corners.mean(axis=1)
        reach = np.linalg.norm(corners - centre[:, None], axis=2).max(axis=1) + radii
        tree = cKDTree(x)
        lists = tree.query_ball_point(centre, reach)
        counts = np.fromiter((len(l) for l in lists), np.intp, nb)
        pv = np.fromiter((i for l in lists for i in l), np.intp, counts.sum())
        pb = np.repeat(np.arange(nb), counts)
        region, dist = closest_feature(x[pv], corners[pb])
        keep = dist < radii[pb]
        if masks is not None:
            allowed = np.asarray(masks[pv, pb]).ravel()
            keep &= allowed
        pv, pb, region, dist = pv[keep], pb[keep], region[keep], dist[keep]
        w = 0.5 * (1.0 + np.cos(np.pi * dist / radii[pb]))                # eq. (12)
        # a vertex exactly on the affection boundary gets w = 0: drop those pairs
        pos = w > 0
        pv, pb, region, dist, w = pv[pos], pb[pos], region[pos], dist[pos], w[pos]

        bound = np.zeros(nv, bool)
        bound[pv] = True
        if unbound == "nearest" and not bound.all():
            lone = np.flatnonzero(~bound)
            # nearest allowed bone by distance to its triangle (dense over bones; lone vertices only)
            lv = np.repeat(lone, nb)
            lb = np.tile(np.arange(nb), len(lone))
            if masks is not None:
                ok = np.asarray(masks[lv, lb]).ravel()
                lv, lb = lv[ok], lb[ok]
            r2, d2 = closest_feature(x[lv], corners[lb])
            order = np.lexsort((d2, lv))
            first = np.ones(len(order), bool)
            first[1:] = lv[order][1:] != lv[order][:-1]
            sel = order[first]
            pv = np.concatenate([pv, lv[sel]])
            pb = np.concatenate([pb, lb[sel]])
            region = np.concatenate([region, r2[sel]])
            w = np.concatenate([w, np.ones(len(sel))])
            bound[lv[sel]] = True

        wsum = np.bincount(pv, weights=w, minlength=nv)
        if unbound == "fade":
            # the rest position is one more "bone" of weight max(0, 1 - sum w): continuous fade to still
            rest_w = np.clip(1.0 - wsum, 0.0, 1.0)
            w = w / np.maximum(wsum, 1.0)[pv]
        else:
            rest_w = (~bound).astype(np.float64)
            w = w / wsum[pv]                                                # eq. (11), normalised

        rest = bone_frames(corners)                                         # (nb, 7, 4, 3)
        frames = rest[pb, region]                                           # (n_pairs, 4, 3)
        inv = np.linalg.inv(frames[:, 1:])                                   # c = (S - origin) F^-1, eq. (1)
        coords = np.einsum("pj,pjk->pk", x[pv] - frames[:, 0], inv)
        wedge = region >= 4
        inplane = coords[:, 0, None] * frames[:, 1] + coords[:, 1, None] * frames[:, 2]
        self.pair_D_ = np.linalg.norm(inplane, axis=1)                      # D of eq. (10)

        # One sparse matrix over Y = [control points; n of every bone; m_i of every bone corner;
        # again m_i; m_{i-1} of every bone corner] (n_controls + 10 n_bones rows; the two extra
        # copies carry the wedge entries). Every frame row is a control-point difference or one of
        # those unit vectors:
        #   A:    s = (1-c1-c2) V_0 + c1 V_1 + c2 V_2 + c3 n
        #   B_i:  s = (1-c1) V_i + c1 V_{i+1} + c2 m_i + c3 n
        #   C_i:  s = V_i + (D/d) (c1 m_i + c2 m_{i-1}) + c3 n        (wedge: rewritten per frame)
        # so the entries of one vertex on a shared control point merge into one.
        nc = len(c)
        n_fixed_cols = nc + 4 * nb
        isA, isB = region == 0, (region >= 1) & (region <= 3)
        side = np.where(isB, region - 1, np.where(wedge, region - 4, 0))          # i of B_i / C_i
        corner = tri[pb]                                                          # (n_pairs, 3)
        ar = np.arange(len(pv))
        vi = corner[ar, side]
        vn = corner[ar, (side + 1) % 3]
        r_, c_, v_ = [], [], []

        def put(mask, col, val):
            r_.append(pv[mask])
            c_.append(col[mask])
            v_.append(val[mask])

        c1, c2, c3 = coords[:, 0], coords[:, 1], coords[:, 2]
        put(isA, corner[:, 0], w * (1 - c1 - c2))
        put(isA, corner[:, 1], w * c1)
        put(isA, corner[:, 2], w * c2)
        put(isB, vi, w * (1 - c1))
        put(isB, vn, w * c1)
        put(isB, nc + nb + 3 * pb + side, w * c2)
        put(wedge, vi, w)
        put(np.ones(len(pv), bool), nc + pb, w * c3)
        rows, cols, vals = np.concatenate(r_), np.concatenate(c_), np.concatenate(v_)
        keys = cols.astype(np.int64) * nv + rows
        uniq, inv = np.unique(keys, return_inverse=True)                          # CSC order, merged
        fdata = np.bincount(inv, weights=vals, minlength=len(uniq))
        frows = (uniq % nv).astype(np.int32)
        findptr = np.concatenate([[0], np.cumsum(np.bincount(uniq // nv, minlength=n_fixed_cols))])
        # The wedge pairs (w c_1 D/d on m_i + m_{i-1}, w (c_2 - c_1) D/d on m_{i-1}; eq. 10) change every frame:
        # evaluated per frame by _add_wedges, the pairs sorted by (bone corner, vertex) so that each corner's
        # pairs are one run and their vertices ascend.
        wi = np.flatnonzero(wedge)
        wcorner = 3 * pb[wi] + side[wi]                                           # which (bone, corner)
        worder = np.lexsort((pv[wi], wcorner))
        wi, wcorner = wi[worder], wcorner[worder]
        D = self.pair_D_[wi]
        c1w, c2w = c1[wi], c2[wi]
        # w c D over d per frame, on the rows m_i + m_{i-1} and m_{i-1}: c_1 m_i + c_2 m_{i-1} =
        # c_1 (m_i + m_{i-1}) + (c_2 - c_1) m_{i-1}, whose terms do not cancel where the corner closes
        self._wedge_num = ((w[wi] * c1w * D).astype(dt), (w[wi] * (c2w - c1w) * D).astype(dt))
        self._wedge_corner = wcorner
        self._wedge_rows = pv[wi].astype(np.int64)
        self._wedge_ptr = np.concatenate([[0], np.cumsum(np.bincount(wcorner, minlength=3 * nb))]).astype(np.int64)
        # d^2 = sq + cross * (1 + g), no cancellation; sq at least the smallest normal number, so that with
        # 1 + g clamped at 0 per bone corner d^2 is positive for every pair without a clamp per pair
        tiny = 1e-300 if dt == np.float64 else float(np.finfo(dt).tiny)
        self._wedge_sq = np.maximum((c1w - c2w) ** 2, tiny).astype(dt)
        self._wedge_cross = (2.0 * c1w * c2w).astype(dt)
        self._fixed_csc = sp.csc_matrix((fdata, frows, findptr), shape=(nv, n_fixed_cols))
        self.dtype_ = dt
        self.triangles_ = tri.astype(np.intp)
        # Displacement form: the fixed columns act on Y - Y_rest and the start value is
        # still + T_fixed Y_rest (the same sum, regrouped, in float64 at bind time), so the
        # float32 product never cancels large absolute coordinates.
        y0, _ = self._bone_vectors(c)
        self._y0 = y0[:n_fixed_cols]
        self._still = (rest_w[:, None] * x + self._fixed_csc @ self._y0).astype(dt)
        self._fixed_csc = self._fixed_csc.astype(dt)
        self._fixed_csr = self._fixed_csc.tocsr()
        self.rest_weight_ = rest_w
        self.n_vertices_, self.n_bones_, self.n_controls_ = nv, nb, len(c)
        self.radii_ = radii
        self.pair_vertex_, self.pair_bone_, self.pair_region_ = pv, pb, region
        self.pair_weight_, self.pair_coords_ = w, coords
        self.bound_ = bound
        self.rest_vertices_ = x
        self.rest_controls_ = c
        return self

    # ------------------------------------------------------------------------------------------
    @property
    def weights(self) -> sp.csr_matrix:
        """(n_vertices, n_bones) normalised blend weights ``w_ij`` of eq. (11)."""
        return sp.csr_matrix((self.pair_weight_, (self.pair_vertex_, self.pair_bone_)),
                             shape=(self.n_vertices_, self.n_bones_))

    def _check_controls(self, control_points) -> np.ndarray:
        if not hasattr(self, "pair_weight_"):
            raise NotFittedError("this PlanarBones is not fitted: call fit(mesh_vertices, control_points, triangles)")
        c = np.asarray(control_points, dtype=np.float64)
        if c.shape[-2:] != (self.n_controls_, 3):
            raise InputError(f"`control_points`: expected shape (..., {self.n_controls_}, 3), got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise InputError("`control_points`: NaN or infinite coordinates; rebuild missing markers first "
                             "(retarget.mocap.clean)")
        return c

    def _y(self, c: np.ndarray):
        """Y (its fixed rows minus their rest values) and the corner dot products ``g``, in ``dtype``."""
        y, g = self._bone_vectors(c)
        y[..., :len(self._y0), :] -= self._y0
        dt = self.dtype_
        return y.astype(dt, copy=False), (1.0 + g).astype(dt, copy=False)

    def _bone_vectors(self, c: np.ndarray):
        """Y and the corner dot products ``g = m_i . m_{i-1}`` for frames ``c`` (..., n_controls, 3), float64.

        Y's rows: control points, then ``n`` of every bone, then ``m_i`` of every bone corner
        ``3 b + i``, then ``m_i + m_{i-1}``, then ``m_{i-1}`` of every bone corner (eqs. 2, 7).
        """
        corners = c[..., self.triangles_, :]
        e = np.roll(corners, -1, axis=-2) - corners                                # eq. (6)
        n = _unit(np.cross(e[..., 0, :], corners[..., 2, :] - corners[..., 0, :]))  # eq. (2)
        m = _unit(np.cross(e, n[..., None, :]))                                    # eq. (7)
        mp = np.roll(m, 1, axis=-2)                                                # m_{i-1}
        g = np.einsum("...i,...i->...", m, mp)
        lead = m.shape[:-3]
        m = m.reshape(lead + (-1, 3))
        mp = mp.reshape(lead + (-1, 3))
        y = np.concatenate([c, n, m, m + mp, mp], axis=-2)
        return y, g.reshape(lead + (-1,))

    def _add_wedges(self, y: np.ndarray, g: np.ndarray, out: np.ndarray) -> None:
        """``out += `` the wedge pairs' part (eq. 10) of frames ``y`` (n, rows of Y, 3), ``g`` (n, 3 n_bones)
        (:meth:`_y`), ``out`` (n, n_vertices, 3)."""
        if len(self._wedge_corner):
            nfc = self._fixed_csc.shape[1]
            nb3 = 3 * self.n_bones_
            _add_wedges(out, y[:, nfc:nfc + nb3], y[:, nfc + nb3:], g, self._wedge_ptr, self._wedge_rows,
                        self._wedge_sq, self._wedge_cross, self._wedge_num[0], self._wedge_num[1])

    def deform(self, control_points) -> np.ndarray:
        """Deformed mesh ``(n_vertices, 3)`` for one frame of the control surface ``(n_controls, 3)``.

        The fixed columns are one sparse product; the wedge pairs (eq. 10) are evaluated by a compiled
        loop; with a second core (and ``self.threads``) a helper thread does the sparse product meanwhile.
        """
        c = self._check_controls(control_points)
        if c.ndim != 2:
            raise InputError(f"`control_points`: expected one frame (n_controls, 3), got {c.shape}; use deform_many")
        y, g = self._y(c)
        out = self._still.copy()
        nfc = self._fixed_csc.shape[1]
        pool = _worker() if self.threads else None
        if pool is None or not len(self._wedge_corner):
            _add_product(self._fixed_csc, y[:nfc], out)
            self._add_wedges(y[None], g[None], out[None])
            return out
        fixed = pool.submit(_add_product, self._fixed_csc, y[:nfc], out)    # fixed part meanwhile
        wedge = np.zeros_like(out)
        self._add_wedges(y[None], g[None], wedge[None])
        fixed.result()
        out += wedge
        return out

    def _deform_range(self, y, g, out, start, stop, chunk) -> None:
        """Frames ``start:stop`` of ``deform_many`` into ``out``."""
        nfc = self._fixed_csr.shape[1]
        nv = self.n_vertices_
        for f0 in range(start, stop, chunk):
            f1 = min(f0 + chunk, stop)
            yb = np.ascontiguousarray(y[f0:f1, :nfc].transpose(1, 0, 2)).reshape(nfc, -1)
            res = (self._fixed_csr @ yb).reshape(nv, f1 - f0, 3)
            # (vertex, frame) -> (frame, vertex) in blocks of vertices that stay in cache, all frames of
            # the chunk at once (a strided pass per frame misses the cache on every vertex)
            for v0 in range(0, nv, 2048):
                np.add(res[v0:v0 + 2048].transpose(1, 0, 2), self._still[v0:v0 + 2048], out=out[f0:f1, v0:v0 + 2048])
            for w0 in range(f0, f1, _WEDGE_FRAMES):
                w1 = min(w0 + _WEDGE_FRAMES, f1)
                self._add_wedges(y[w0:w1], g[w0:w1], out[w0:w1])

    def deform_many(self, control_points, chunk: int = 32) -> np.ndarray:
        """Deformed meshes ``(n_frames, n_vertices, 3)`` for ``(n_frames, n_controls, 3)``.

        The bone frames of all frames are one batched call, the fixed part of the map one sparse product for
        ``chunk`` frames at a time, the wedge pairs one compiled pass; with ``self.threads`` a helper thread does the
        second half of the take.
        """
        c = self._check_controls(control_points)
        if c.ndim != 3:
            raise InputError(f"`control_points`: expected (n_frames, n_controls, 3), got {c.shape}")
        y, g = self._y(c)
        out = np.empty((len(c), self.n_vertices_, 3), self.dtype_)
        pool = _worker() if self.threads else None
        if pool is None or len(c) < 2 * chunk:
            self._deform_range(y, g, out, 0, len(c), chunk)
            return out
        mid = len(c) // 2
        other = pool.submit(self._deform_range, y, g, out, mid, len(c), chunk)
        self._deform_range(y, g, out, 0, mid, chunk)
        other.result()
        return out


@njit(cache=True, nogil=True, error_model="numpy")     # numpy's model: divisions vectorise (d > 0 always)
def _add_wedges(out, y_sum, y_prev, g, ptr, rows, sq, cross, num_sum, num_prev):
    """``out[f, v] += (w c_1 D / d) (m_i' + m_{i-1}') + (w (c_2 - c_1) D / d) m_{i-1}'`` for every wedge pair of
    every frame ``f`` (eq. 10; the pair's vertex ``v = rows[p]``, corner ``i`` of bone ``b``).

    ``y_sum``, ``y_prev`` (n_frames, 3 n_bones, 3): ``m_i' + m_{i-1}'`` and ``m_{i-1}'`` of each bone corner;
    ``g`` (n_frames, 3 n_bones): ``1 + m_i' . m_{i-1}'``; the pairs of corner ``k`` are ``ptr[k]:ptr[k + 1]``
    with ``sq = (c_1 - c_2)^2``, ``cross = 2 c_1 c_2`` and the numerators ``num_sum = w c_1 D``,
    ``num_prev = w (c_2 - c_1) D``. The wedge length ``d = sqrt(sq + cross max(g, 0))``
    (:class:`PlanarBones`), computed in the arrays' precision.
    """
    n_frames = out.shape[0]
    longest = 0
    for k in range(ptr.size - 1):
        longest = max(longest, ptr[k + 1] - ptr[k])
    ks = np.empty(longest, sq.dtype)
    kp = np.empty(longest, sq.dtype)
    for k in range(ptr.size - 1):
        p0, p1 = ptr[k], ptr[k + 1]
        n = p1 - p0
        # this corner's pairs as slices (indexed from 0: no test for negative indices in the loops)
        sq_k, cross_k, ns_k, np_k, rows_k = sq[p0:p1], cross[p0:p1], num_sum[p0:p1], num_prev[p0:p1], rows[p0:p1]
        for f in range(n_frames):
            gk = g[f, k]
            if gk < 0:
                gk = gk * 0                     # (in the arrays' precision)
            # the factors first, a loop without scatter (vectorised square roots and divisions)
            for i in range(n):
                r = 1 / np.sqrt(sq_k[i] + cross_k[i] * gk)
                ks[i] = ns_k[i] * r
                kp[i] = np_k[i] * r
            u0, u1, u2 = y_sum[f, k, 0], y_sum[f, k, 1], y_sum[f, k, 2]
            w0, w1, w2 = y_prev[f, k, 0], y_prev[f, k, 1], y_prev[f, k, 2]
            o = out[f]
            for i in range(n):
                v = np.uint64(rows_k[i])        # unsigned: no test for a negative index
                o[v, 0] += ks[i] * u0 + kp[i] * w0
                o[v, 1] += ks[i] * u1 + kp[i] * w1
                o[v, 2] += ks[i] * u2 + kp[i] * w2


_POOL: ThreadPoolExecutor | None = None


def _worker() -> ThreadPoolExecutor | None:
    """One helper thread (scipy's sparse kernels release the GIL), or None on a single core."""
    global _POOL
    if _POOL is None and (os.cpu_count() or 1) > 1:
        _POOL = ThreadPoolExecutor(1, thread_name_prefix="planar-bones")
    return _POOL


def _add_product(a: sp.csc_matrix, x: np.ndarray, out: np.ndarray) -> None:
    """``out += a @ x`` for a CSC ``a``, C-contiguous ``x`` (n_cols, k) and ``out`` (n_rows, k)."""
    if _csc_matvecs is not None and a.indices.dtype == a.indptr.dtype and out.flags.c_contiguous:
        _csc_matvecs(a.shape[0], a.shape[1], x.shape[1], a.indptr, a.indices, a.data,
                     np.ascontiguousarray(x).ravel(), out.reshape(-1))
    else:
        out += a @ x


def triangle_min_angles(corners: np.ndarray) -> np.ndarray:
    """Smallest interior angle (radians) of each triangle ``(n, 3, 3)``; 0 for collinear corners."""
    a = np.roll(corners, -1, axis=1) - corners
    b = np.roll(corners, 1, axis=1) - corners
    na = np.linalg.norm(a, axis=2)
    nb = np.linalg.norm(b, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        cosang = np.einsum("nij,nij->ni", a, b) / (na * nb)
    ang = np.arccos(np.clip(np.nan_to_num(cosang, nan=1.0), -1.0, 1.0))
    return ang.min(axis=1)
