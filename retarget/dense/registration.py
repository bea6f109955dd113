"""Mesh registration: fit a reference face mesh onto a target (section 6 of 001_7296bf6ea73cabea.txt).

Design notes and figures: docs/keypoints.md, "Notes on the code", ``retarget/dense/registration.py``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.optimize import minimize
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from keyshape.base.errors import InputError
from keyshape.retarget.dense.keypoints import farthest_point_sample
from keyshape.retarget.dense.meshcheck import TriangleSurface, check_mesh, component_of, edges, interior_edge_faces
from keyshape.retarget.rbf import RBF


def resolve_landmarks(pairs: list, ref_vertices: np.ndarray, tgt_vertices: np.ndarray,
                      source: str = "landmarks") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Turn ``[{"reference": R, "target": T}, ...]`` into point arrays.

    Each of R and T is a vertex index or an ``[x, y, z]`` point. Returns
    (reference points (L, 3), target points (L, 3), reference vertex index or
    -1 per landmark). Raises :class:`InputError` naming ``source`` for
    missing vertices, malformed entries and fewer than 4 pairs.
    """
    if not isinstance(pairs, list):
        raise InputError(f"expected a list of {{'reference': R, 'target': T}} pairs, got {type(pairs).__name__}",
                         source)
    if len(pairs) < 4:
        raise InputError(f"{len(pairs)} landmark pair(s): at least 4 are needed (10-12 recommended)", source)
    out = {"reference": [], "target": []}
    for i, p in enumerate(pairs):
        if not isinstance(p, dict) or set(p) != {"reference", "target"}:
            raise InputError(f"pair {i}: expected {{'reference': R, 'target': T}}, got {p!r:.80}", source)
        for side, verts in (("reference", ref_vertices), ("target", tgt_vertices)):
            x = p[side]
            if isinstance(x, bool):
                x = None
            if isinstance(x, int):
                if not 0 <= x < len(verts):
                    raise InputError(f"pair {i}: {side} vertex {x} does not exist "
                                     f"(the {side} mesh has vertices 0..{len(verts) - 1})", source)
                out[side].append(verts[x])
            elif isinstance(x, list) and len(x) == 3 and all(isinstance(c, (int, float)) and not isinstance(c, bool)
                                                             for c in x) and np.all(np.isfinite(x)):
                out[side].append(np.array(x, np.float64))
            else:
                raise InputError(f"pair {i}: {side} must be a vertex index or [x, y, z], got {x!r:.60}", source)
    r, t = np.array(out["reference"]), np.array(out["target"])
    d = np.linalg.norm(r[:, None] - r[None], axis=2)
    np.fill_diagonal(d, np.inf)
    if d.min() < 1e-9:
        i, j = np.unravel_index(np.argmin(d), d.shape)
        raise InputError(f"pairs {i} and {j} name the same reference point", source)
    for side, pts in (("reference", r), ("target", t)):
        c = pts - pts.mean(0)
        sv = np.linalg.svd(c, compute_uv=False)
        if sv[0] <= 1e-9 * max(1.0, np.abs(pts).max()):
            raise InputError(f"all {len(pts)} {side} landmarks are on one point: they must spread over the face",
                             source)
        if sv[1] <= 1e-6 * sv[0]:
            raise InputError(f"the {side} landmarks lie on one line: they must spread over the face", source)
        dt = np.linalg.norm(pts[:, None] - pts[None], axis=2)
        np.fill_diagonal(dt, np.inf)
        if side == "target" and dt.min() < 1e-9 * max(1.0, np.abs(pts).max()):
            i, j = np.unravel_index(np.argmin(dt), dt.shape)
            raise InputError(f"pairs {i} and {j} send two reference points to the same target point", source)
    return r, t, np.array([p["reference"] if isinstance(p["reference"], int) else -1 for p in pairs], np.intp)


def landmark_warp(vertices: np.ndarray, ref_points: np.ndarray, tgt_points: np.ndarray) -> np.ndarray:
    """Thin-plate RBF warp sending ``ref_points`` exactly to ``tgt_points``.

    The warp carries an affine part (scale, rotation, shear between faces)
    when the reference landmarks span 3D; coplanar landmarks cannot fix an
    affine map, so the warp is then a linear-kernel (``r``) RBF with a
    translation only (the thin plate needs the affine part to be solvable).
    """
    spread = np.linalg.matrix_rank(ref_points - ref_points.mean(0), tol=1e-6 * np.ptp(ref_points))
    if spread == 3:
        rbf = RBFInterpolator(ref_points, tgt_points - ref_points, kernel="thin_plate_spline", degree=1)
    else:
        rbf = RBFInterpolator(ref_points, tgt_points - ref_points, kernel="linear", degree=0)
    return vertices + rbf(vertices)


@dataclass
class RegistrationResult:
    """What :func:`register_mesh` returns: fitted vertices, start, energies and timings."""

    vertices: np.ndarray            # (n_vertices, 3) fitted reference vertices
    start: np.ndarray               # after landmark warp and control projection
    warped: np.ndarray              # after the landmark warp only
    energy_start: float
    energy: float
    n_evals: int
    seconds: float
    solver: str
    converged: bool
    terms: dict = field(default_factory=dict)


class MeshEnergy:
    """E of eq. (17) and its gradient over control displacements ``D`` (n_controls, 3).

    Everything that does not change per evaluation (B, edges, rest lengths
    and bends, the target's closest-point structure) is built here once;
    one evaluation is ``V = V0 + B D``, one closest-point query and
    scatter-adds for the edge terms.
    """

    def __init__(self, v0, triangles, basis, fit, surface, alpha, beta, gamma, delta, lm_idx, lm_tgt):
        self.v0, self.tri, self.B = v0, triangles, basis
        self.fit, self.surface = fit, surface
        self.alpha, self.beta, self.gamma, self.delta = alpha, beta, gamma, delta
        self.lm_idx, self.lm_tgt = lm_idx, lm_tgt
        self.edges, _, _ = edges(triangles)
        n = len(v0)
        ne, nf = len(self.edges), len(triangles)
        # sparse scatter matrices: gradient of per-edge / per-face vectors onto vertices (one matmul each)
        self._E = csr_matrix((np.r_[np.ones(ne), -np.ones(ne)], (np.r_[self.edges[:, 1], self.edges[:, 0]],
                             np.r_[np.arange(ne), np.arange(ne)])), shape=(n, ne))
        self._F = [csr_matrix((np.ones(nf), (triangles[:, j], np.arange(nf))), shape=(n, nf)) for j in range(3)]
        self._fitm = csr_matrix((np.ones(len(fit)), (fit, np.arange(len(fit)))), shape=(n, len(fit)))
        self.len0 = np.linalg.norm(v0[self.edges[:, 1]] - v0[self.edges[:, 0]], axis=1)
        self.fpairs, _ = interior_edge_faces(triangles)
        self.bend0 = self._bend(v0)[0]
        npair = len(self.fpairs)
        self._P0, self._P1 = (csr_matrix((np.ones(npair), (self.fpairs[:, j], np.arange(npair))), shape=(nf, npair))
                              for j in range(2))
        self.n_evals = 0

    def _normals(self, v):
        a, b, c = v[self.tri[:, 0]], v[self.tri[:, 1]], v[self.tri[:, 2]]
        cr = np.cross(b - a, c - a)
        nrm = np.linalg.norm(cr, axis=1)
        return a, b, c, cr, nrm

    def _bend(self, v):
        a, b, c, cr, nrm = self._normals(v)
        n = cr / nrm[:, None]
        return np.einsum("ij,ij->i", n[self.fpairs[:, 0]], n[self.fpairs[:, 1]]), (a, b, c, n, nrm)

    def vertices(self, d: np.ndarray) -> np.ndarray:
        return self.v0 + self.B @ d.reshape(-1, 3)

    def terms(self, v: np.ndarray) -> dict:
        q, _ = self.surface.closest(v[self.fit])
        ev = v[self.edges[:, 1]] - v[self.edges[:, 0]]
        bend, _ = self._bend(v)
        out = dict(dist=float(np.mean(np.sum((v[self.fit] - q) ** 2, 1))),
                   strain=float(np.mean((np.linalg.norm(ev, axis=1) - self.len0) ** 2)),
                   bend=float(np.mean((bend - self.bend0) ** 2)))
        out["landmarks"] = float(np.mean(np.sum((v[self.lm_idx] - self.lm_tgt) ** 2, 1))) if len(self.lm_idx) else 0.0
        return out

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        self.n_evals += 1
        v = self.vertices(x)
        g = np.zeros_like(v)
        # E_dist
        vf = v[self.fit]
        q, _ = self.surface.closest(vf)
        r = vf - q
        e_dist = np.mean(np.sum(r * r, 1))
        g += self._fitm @ (2.0 * self.alpha / len(vf) * r)
        # E_strain
        ev = v[self.edges[:, 1]] - v[self.edges[:, 0]]
        ln = np.linalg.norm(ev, axis=1)
        s = ln - self.len0
        e_strain = np.mean(s * s)
        ge = (2.0 * self.beta / len(s) * s / ln)[:, None] * ev
        g += self._E @ ge
        # E_bend: d(n1.n2) = n2.dn1 + n1.dn2, dn = (I - n n^T) dcr / |cr|, cr = (b - a) x (c - a)
        bend, (a, b, c, n, nrm) = self._bend(v)
        db = bend - self.bend0
        e_bend = np.mean(db * db) if len(db) else 0.0
        if len(db):
            coef = 2.0 * self.gamma / len(db) * db
            gn = self._P0 @ (coef[:, None] * n[self.fpairs[:, 1]]) + self._P1 @ (coef[:, None] * n[self.fpairs[:, 0]])
            gcr = (gn - n * np.einsum("ij,ij->i", n, gn)[:, None]) / nrm[:, None]
            g1 = np.cross(c - a, gcr)  # d/d(b - a) of gcr.((b - a) x (c - a))
            g2 = np.cross(gcr, b - a)  # d/d(c - a)
            g += self._F[1] @ g1 + self._F[2] @ g2 - self._F[0] @ (g1 + g2)
        # landmarks
        e_lm = 0.0
        if len(self.lm_idx):
            rl = v[self.lm_idx] - self.lm_tgt
            e_lm = np.mean(np.sum(rl * rl, 1))
            np.add.at(g, self.lm_idx, 2.0 * self.delta / len(rl) * rl)
        e = self.alpha * e_dist + self.beta * e_strain + self.gamma * e_bend + self.delta * e_lm
        return float(e), (self.B.T @ g).ravel()


#: the weights of E_dist, E_strain, E_bend (eq. 17) and of the landmark term; the control RBF's ridge
WEIGHTS, SMOOTHING = (1.0, 1.0, 0.01, 1.0), 1e-6


def register_mesh(ref_vertices: np.ndarray, ref_triangles: np.ndarray, tgt_vertices: np.ndarray,
                  tgt_triangles: np.ndarray, pairs: list, *, solver: str = "lbfgs", n_controls: int = 200,
                  max_evals: int = 200, source: str = "landmarks") -> RegistrationResult:
    """Fit the reference mesh onto the target (section 6 of 001); see the module notes.

    Parameters
    ----------
    ref_vertices, ref_triangles, tgt_vertices, tgt_triangles : the two meshes (triangles (n, 3)).
    pairs : landmark pairs (see :func:`resolve_landmarks`).
    solver : ``"lbfgs"`` (analytic gradients, default) or ``"simplex"`` (Nelder-Mead baseline).
    n_controls : number of control vertices (farthest-point sampled on the fitted shell, landmarks included).
    max_evals : energy evaluations allowed to the solver.

    The energy's weights are :data:`WEIGHTS`; the control vertices are sampled with seed 0 and interpolated
    by a Gaussian RBF with the ridge :data:`SMOOTHING`.

    Only the reference shell holding the landmarks is pulled to the target,
    and only onto the target shell holding its landmarks (other shells such
    as eyes and teeth follow the control deformation).
    """
    if solver not in ("lbfgs", "simplex"):
        raise InputError(f"solver must be 'lbfgs' or 'simplex', got {solver!r}")
    rv, rt = check_mesh(ref_vertices, ref_triangles, "reference mesh")
    tv, tt = check_mesh(tgt_vertices, tgt_triangles, "target mesh")
    lr, lt, lidx = resolve_landmarks(pairs, rv, tv, source)
    t0 = time.perf_counter()
    warped = landmark_warp(rv, lr, lt)
    # shells holding the landmarks
    seeds_r = lidx[lidx >= 0] if (lidx >= 0).any() else np.unique(TriangleSurface(rv, rt).closest(lr)[1])
    fit = np.flatnonzero(component_of(len(rv), rt, seeds_r if (lidx >= 0).any() else rt[seeds_r].ravel()))
    tgt_face_near = TriangleSurface(tv, tt).closest(lt)[1]
    tmask = component_of(len(tv), tt, tt[tgt_face_near].ravel())
    surface = TriangleSurface(tv, tt[tmask[tt].all(1)])
    # control vertices: landmark vertices + farthest-point samples of the fitted shell
    rng = np.random.default_rng(0)
    n_c = min(n_controls, len(fit))
    ctrl = fit[farthest_point_sample(warped[fit], n_c, rng)]
    ctrl = np.unique(np.concatenate([lidx[lidx >= 0], ctrl]))
    cw = warped[ctrl]
    rbf = RBF("gaussian", affine=False, sigma_scale=1.5, smoothing=SMOOTHING).fit(cw)
    basis = rbf.interpolation_matrix(warped)                                   # (n_vertices, n_controls)
    # start: control vertices projected onto the target surface
    d0 = surface.closest(cw)[0] - cw
    # the energy lives on the fitted shell only, re-indexed 0..len(fit)-1
    local = np.full(len(rv), -1, np.intp)
    local[fit] = np.arange(len(fit))
    shell_tris = local[rt[np.isin(rt, fit).all(1)]]
    lm_local = local[lidx[lidx >= 0]]
    energy = MeshEnergy(warped[fit], shell_tris, np.ascontiguousarray(basis[fit]), np.arange(len(fit)), surface,
                        *WEIGHTS, lm_local, lt[lidx >= 0])
    x0 = d0.ravel()
    start = warped + basis @ d0
    e_start = energy(x0)[0]
    if solver == "lbfgs":
        res = minimize(energy, x0, jac=True, method="L-BFGS-B",
                       options=dict(maxfun=max_evals, maxiter=max_evals, ftol=1e-12, gtol=1e-10))
    else:
        res = minimize(lambda x: energy(x)[0], x0, method="Nelder-Mead",
                       options=dict(maxfev=max_evals, xatol=1e-6, fatol=1e-12, adaptive=True))
    fitted = warped + basis @ res.x.reshape(-1, 3)
    return RegistrationResult(vertices=fitted, start=start, warped=warped, energy_start=float(e_start),
                              energy=float(res.fun), n_evals=energy.n_evals, seconds=time.perf_counter() - t0,
                              solver=solver, converged=bool(res.success), terms=energy.terms(fitted[fit]))


def place_markers(markers: dict, ref_vertices: np.ndarray, ref_triangles: np.ndarray, fitted: np.ndarray,
                  tgt_vertices: np.ndarray, tgt_triangles: np.ndarray, source: str = "markers") -> dict:
    """Carry reference markers onto the target (what the mocap path needs from a new face).

    A marker is a reference vertex index or an ``[x, y, z]`` point (taken at
    its closest point on the reference surface, in barycentric coordinates).
    Its fitted position is projected onto the target surface. Returns
    ``{name: {"position": [x, y, z], "vertex": nearest target vertex}}``.
    """
    names = list(markers)
    pts = np.empty((len(names), 3))
    for i, k in enumerate(names):
        m = markers[k]
        if isinstance(m, (int, np.integer)):
            if not 0 <= m < len(ref_vertices):
                raise InputError(f"marker {k!r}: vertex {m} does not exist (0..{len(ref_vertices) - 1})", source)
            pts[i] = fitted[m]
        else:
            p = np.asarray(m, np.float64)
            q, f = TriangleSurface(ref_vertices, ref_triangles).closest(p[None])
            a, b, c = ref_vertices[ref_triangles[f[0]]]
            bary = np.linalg.lstsq(np.stack([a, b, c], 1), q[0], rcond=None)[0]
            pts[i] = bary @ fitted[ref_triangles[f[0]]]
    on_target, _ = TriangleSurface(tgt_vertices, tgt_triangles).closest(pts)
    _, near = cKDTree(tgt_vertices).query(on_target)
    return {k: {"position": [float(x) for x in on_target[i]], "vertex": int(near[i])} for i, k in enumerate(names)}


def transfer_masks(masks: dict, fitted: np.ndarray, tgt_vertices: np.ndarray, source: str = "masks") -> dict:
    """Discontinuity masks (reference vertex groups) onto the target (section 6.1 of 001).

    The paper renders the mask through a cylindrical projection into the
    target's texture; with the fitted reference lying on the target, a
    target vertex belongs to a mask when its nearest fitted reference vertex
    does, which works for any target resolution. Returns {name: sorted target indices}.
    """
    _, near = cKDTree(fitted).query(tgt_vertices)
    out = {}
    for k, idx in masks.items():
        idx = np.asarray(idx, np.intp)
        if len(idx) and (idx.min() < 0 or idx.max() >= len(fitted)):
            raise InputError(f"mask {k!r}: vertex indices must lie in 0..{len(fitted) - 1}", source)
        member = np.zeros(len(fitted), bool)
        member[idx] = True
        out[k] = np.flatnonzero(member[near])
    return out
