"""The one radial-basis-function class of keyshape: marker retargeting (001 section 5.1) and
the Gaussian face-space deformation of the dense tools (002 section 4).

Kernels: ``imq`` (inverse multiquadric with a per-centre radius, eqs. (15)-(16) of 001), ``tps`` (``d**2 log d``),
``gaussian`` (eq. (5) of 002, one fixed ``sigma``). With the affine term the system is eq. (14) of 001 bordered by
``[U 1]``, so an affine motion of all markers is reproduced exactly; without it (002) the displacement ``V - U`` is
interpolated. ``smoothing`` adds a ridge ``Phi + lambda I``. The derivations and figures: docs/retarget.md,
"Notes on the code", ``retarget/rbf.py``.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, lu_factor, lu_solve
from scipy.spatial.distance import cdist

from keyshape.base.errors import InputError, NotFittedError

KERNELS = ("imq", "tps", "gaussian")


def _sanitize_points(x, name: str, n: int | None = None, allow_frames: bool = False) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    ok_ndim = (2, 3) if allow_frames else (2,)
    if a.ndim not in ok_ndim or a.shape[-1] != 3:
        want = "(n_markers, 3)" + (" or (n_frames, n_markers, 3)" if allow_frames else "")
        raise InputError(f"`{name}`: expected an array of shape {want}, got shape {a.shape}")
    if n is not None and a.shape[-2] != n:
        raise InputError(f"`{name}`: expected {n} markers (one per source centre), got {a.shape[-2]}")
    if not np.all(np.isfinite(a)):
        bad = np.flatnonzero(~np.isfinite(a).reshape(-1, a.shape[-2], 3).all(axis=(0, 2)))
        raise InputError(f"`{name}`: markers {bad[:10].tolist()} are NaN or infinite; "
                         "fill or drop gaps before fitting (see retarget.mocap.clean)")
    return a


def pairwise_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distances (len(a), len(b)) in float64."""
    return cdist(np.asarray(a, np.float64), np.asarray(b, np.float64))


class RBF:
    """Scattered-data map ``f`` with ``f(source_i) = target_i`` (eqs. 13-16 of 001; eqs. 1-5 of 002).

    Parameters
    ----------
    kernel : {"imq", "tps", "gaussian"}
    affine : bool, optional
        Solve the affine term with the weights (eq. 14). Default True for ``imq`` and
        ``tps``, False for ``gaussian`` (002's formulation, displacement interpolation).
    radius_scale : float
        Multiplies the per-centre radii of eq. (16) (``imq`` only).
    sigma : float, optional
        Gaussian width; default ``sigma_scale`` times the median nearest-neighbour distance
        of the centres.
    sigma_scale : float
        See ``sigma`` (1.0 for marker retargeting; the dense tools use 1.25 and 1.5).
    smoothing : float
        Ridge ``lambda`` added to the diagonal of ``Phi`` (0: exact interpolation).
    labels : sequence of str, optional
        Names of the centres, used only in error messages.

    Attributes
    ----------
    centres_ : (n_markers, 3) source points
    radii_ : (n_markers,) per-centre radius (imq) or ``sigma`` repeated (gaussian)
    sigma_ : float, the Gaussian width used (NaN for the other kernels)
    affine_ : bool, whether the affine term is solved
    coef_ : (n_markers + 4, 3) or (n_frames, n_markers + 4, 3), set by ``fit(source, target)``
        RBF weights ``alpha`` then the affine block ``P`` (4 x 3, rows x, y, z, 1);
        the affine block is zero when ``affine`` is False.
    """

    def __init__(self, kernel: str = "imq", affine: bool | None = None, radius_scale: float = 1.0,
                 sigma: float | None = None, sigma_scale: float = 1.0, smoothing: float = 0.0, labels=None):
        self.kernel = kernel
        self.affine = affine
        self.radius_scale = radius_scale
        self.sigma = sigma
        self.sigma_scale = sigma_scale
        self.smoothing = smoothing
        self.labels = labels

    # -- basis -------------------------------------------------------------------------------
    def _phi(self, d: np.ndarray) -> np.ndarray:
        if self.kernel == "imq":
            return 1.0 / np.sqrt(d * d + self.radii_ ** 2)
        if self.kernel == "tps":
            with np.errstate(divide="ignore", invalid="ignore"):
                out = d * d * np.log(d)
            out[d == 0] = 0.0
            return out
        return np.exp(-(d * d) / (2.0 * self.radii_ ** 2))

    def kernel_matrix(self, points) -> np.ndarray:
        """``phi_i(|x_p - u_i|)`` for ``points`` (n_points, 3): (n_points, n_markers)."""
        self._check_fitted()
        x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self._phi(pairwise_distances(x, self.centres_))

    def basis(self, points) -> np.ndarray:
        """The evaluation matrix ``(n_points, n_markers + 4)``: ``f(points) = basis @ coef_``
        (plus ``points`` without the affine term).

        Precompute it once when the same points are mapped for many frames
        (the dense deformer baseline).
        """
        x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.hstack([self.kernel_matrix(x), x, np.ones((len(x), 1))])

    # -- fit / call --------------------------------------------------------------------------
    def fit(self, source, target=None) -> "RBF":
        """Factor the system of the centres ``source``; with ``target``, also solve eq. (14) for
        ``f(source) = target`` (``coef_``).

        Parameters
        ----------
        source : (n_markers, 3) centres (e.g. the neutral frame of the mocap, the rest key points)
        target : (n_markers, 3) or (n_frames, n_markers, 3), optional

        Raises
        ------
        InputError
            Wrong shapes, NaN markers, fewer than 4 (affine) centres, coincident centres,
            a bad ``sigma``/``smoothing``, or a degenerate (coplanar) centre set for the affine term.
        """
        if self.kernel not in KERNELS:
            raise InputError(f"kernel: expected one of {', '.join(KERNELS)}, got {self.kernel!r}")
        if not self.smoothing >= 0:
            raise InputError(f"smoothing must be >= 0, got {self.smoothing}")
        u = _sanitize_points(source, "source")
        n = len(u)
        affine = (self.kernel != "gaussian") if self.affine is None else bool(self.affine)
        if n < (4 if affine else 1):
            raise InputError(f"`source`: need at least 4 markers for the affine term, got {n}")
        d = pairwise_distances(u, u)
        scale = float(np.max(d)) if n > 1 else 1.0
        off = d.copy()
        np.fill_diagonal(off, np.inf)
        nn = off.min(axis=1) if n > 1 else np.array([1.0])
        if n > 1 and nn.min() <= 1e-9 * max(scale, 1e-300):
            i, j = np.unravel_index(np.argmin(off), off.shape)
            name = (lambda k: f"{k} ({self.labels[k]!r})") if self.labels is not None else str
            raise InputError(f"`source`: centres {name(i)} and {name(j)} coincide (distance {off[i, j]:.3g}); "
                             "an RBF needs distinct centres: drop or merge duplicate markers")
        self.sigma_ = float("nan")
        if self.kernel == "imq":
            self.radii_ = self.radius_scale * nn
        elif self.kernel == "gaussian":
            sigma = self.sigma_scale * float(np.median(nn)) if self.sigma is None else float(self.sigma)
            if not sigma > 0:
                raise InputError(f"sigma: expected a positive width, got {sigma}")
            self.radii_ = np.full(n, sigma)
            self.sigma_ = sigma
        else:
            self.radii_ = np.zeros(n)
        self.centres_ = u
        self.affine_ = affine
        phi = self._phi(d)
        phi[np.diag_indices_from(phi)] += self.smoothing
        if affine:
            poly = np.hstack([u, np.ones((n, 1))])
            rank = np.linalg.matrix_rank(poly - poly.mean(axis=0) * [1, 1, 1, 0], tol=1e-9 * scale)
            if rank < 4:
                raise InputError(f"`source`: the affine term needs markers spanning 3D, but they lie on a "
                                 f"{'plane' if rank == 3 else 'line' if rank == 2 else 'point'} "
                                 f"(the matrix [U 1] has rank {rank}/4); use affine=False")
            a = np.zeros((n + 4, n + 4))
            a[:n, :n] = phi
            a[:n, n:] = poly
            a[n:, :n] = poly.T
        else:
            a = phi
        if self.kernel == "gaussian" and not affine:         # symmetric positive definite
            a[np.diag_indices_from(a)] += 1e-12
            try:
                self._solve = ("cho", cho_factor(a, lower=True, check_finite=False))
            except np.linalg.LinAlgError:
                raise InputError("`source`: the gaussian system is singular for these centres") from None
        else:
            lu = lu_factor(a, check_finite=False)
            diag = np.abs(np.diag(lu[0]))
            if not np.all(np.isfinite(lu[0])) or np.min(diag) < 1e-14 * np.max(diag):
                raise InputError(f"`source`: the {self.kernel} system is singular for these centres")
            self._solve = ("lu", lu)
        if hasattr(self, "coef_"):
            del self.coef_
        if target is not None:
            self.coef_ = self.weights(target)
        return self

    def _lin_solve(self, rhs: np.ndarray) -> np.ndarray:
        kind, fac = self._solve
        return (cho_solve if kind == "cho" else lu_solve)(fac, rhs, check_finite=False)

    def weights(self, target) -> np.ndarray:
        """Coefficients (as ``coef_``) of the map sending the centres to ``target``
        ((n_markers, 3) -> (n_markers + 4, 3); (n_frames, n_markers, 3) -> (n_frames, n_markers + 4, 3))."""
        self._check_fitted()
        u = self.centres_
        n = len(u)
        v = _sanitize_points(target, "target", n=n, allow_frames=True)
        frames = v.reshape(-1, n, 3)
        rhs = frames if self.affine_ else frames - u  # displacement interpolation without the affine term
        if self.affine_:
            rhs = np.concatenate([rhs, np.zeros((len(frames), 4, 3))], axis=1)
        # one factorisation, all frames: columns are (frame, xyz)
        sol = self._lin_solve(rhs.transpose(1, 0, 2).reshape(len(rhs[0]), -1))
        sol = sol.reshape(-1, len(frames), 3).transpose(1, 0, 2)
        if not self.affine_:
            coef = np.zeros((len(frames), n + 4, 3))
            coef[:, :n] = sol
            sol = coef
        return sol[0] if v.ndim == 2 else sol

    def interpolation_matrix(self, points) -> np.ndarray:
        """(n_points, n_markers) ``M`` with ``f(points) = points + M @ (target - source)`` (no affine term)."""
        if self.affine_:
            raise InputError("interpolation_matrix: only for affine=False (displacement interpolation)")
        return np.ascontiguousarray(self._lin_solve(self.kernel_matrix(points).T).T)

    def _check_fitted(self):
        if not hasattr(self, "centres_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit(source, target) first")

    def _evaluate(self, points, coef) -> np.ndarray:
        x = np.asarray(points, dtype=np.float64)
        if x.shape[-1] != 3:
            raise InputError(f"`points`: expected shape (..., 3), got {x.shape}")
        b = self.basis(x.reshape(-1, 3))
        out = np.einsum("pk,...kc->...pc", b, coef)
        if not self.affine_:
            out = out + x.reshape(-1, 3)
        return out.reshape(coef.shape[:-2] + x.shape)

    def __call__(self, points) -> np.ndarray:
        """Map ``points`` (..., 3) by the fitted ``coef_``; with a multi-frame fit, returns (n_frames, ..., 3)."""
        self._check_fitted()
        if not hasattr(self, "coef_"):
            raise NotFittedError(f"this {type(self).__name__} has no target: call fit(source, target) "
                                 "or use deform(points, target)")
        return self._evaluate(points, self.coef_)

    def deform(self, points, target) -> np.ndarray:
        """Map ``points`` (n_points, 3) by the map sending the centres to ``target`` ((n_markers, 3)
        -> (n_points, 3), or (n_frames, n_markers, 3) -> (n_frames, n_points, 3)); ``coef_`` is untouched."""
        return self._evaluate(points, self.weights(target))
