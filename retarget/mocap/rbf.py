"""Radial-basis-function mapping between two labelled marker sets (section 5.1 of 001_7296bf6ea73cabea.txt).

``RBFRetarget(kernel).fit(source, target)`` solves once; the fitted object maps
any points (``__call__``). ``target`` may hold many frames at once
(``(n_frames, n_markers, 3)``): the system is factored once and solved for all
right-hand sides, and evaluation is one matrix product per frame, so the same
class serves as the dense RBF *deformer* baseline (002_dce09d5f5656b088.txt,
section 4) driven by per-frame markers.

Kernels
-------
``imq``      inverse multiquadric, eq. (15): ``phi_i(d) = 1 / sqrt(d**2 + r_i**2)`` with a
             per-centre radius, eq. (16): ``r_i = min_{j != i} |x_i - x_j|`` (times ``radius_scale``).
``tps``      thin-plate spline ``phi(d) = d**2 log d`` (``0`` at ``d = 0``).
``gaussian`` eq. (5) of 002: ``phi(d) = exp(-d**2 / (2 sigma**2))`` with one fixed ``sigma`` for
             every centre (002 fixes it so the matrix stays invertible); the constant
             ``1/(sqrt(2 pi) sigma)`` of the extracted text cancels in the solve and is dropped.
             The extracted text reads ``e^{-x/sigma}``; the square is restored as for any
             Gaussian.

Affine term
-----------
Eq. (14) of 001 appends the source points ``U`` as extra columns and rows; for an
*affine* ``p_m`` the columns must be ``[U, 1]`` (the flattened equation drops the
ones), giving the bordered system::

    [ Phi    [U 1] ] [alpha]   [V]
    [ [U 1]^T   0  ] [  P  ] = [0]        Phi[k, i] = phi_i(|u_k - u_i|)

The last block row ``[U 1]^T alpha = 0`` makes ``alpha = 0, P = affine`` the unique
solution whenever ``V`` is an affine image of ``U``: an affine (in particular rigid)
motion of all markers is reproduced *exactly* everywhere, not only at the centres.
Without the affine term (``affine=False``, the 002 formulation) we interpolate the
*displacement* ``V - U`` and return ``x + sum_i alpha_i phi_i``: 002's eq. (3) read
literally interpolates positions, which would send every point far from the key
points to the origin, and its figure 2 draws control *vectors*; interpolating the
displacement is the reading under which zero motion leaves every point still.

Examples
--------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> src = rng.normal(size=(20, 3)); tgt = 1.1 * src + 0.05 * rng.normal(size=(20, 3))
>>> f = RBFRetarget("imq").fit(src, tgt)
>>> bool(np.allclose(f(src), tgt))
True
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import lu_factor, lu_solve
from scipy.spatial.distance import cdist

from keyshape.base.errors import InputError, KeyshapeError

KERNELS = ("imq", "tps", "gaussian")


class NotFittedError(KeyshapeError, ValueError, AttributeError):
    """An estimator was used before ``fit``."""


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


class RBFRetarget:
    """Scattered-data map ``f`` with ``f(source_i) = target_i`` (eqs. 13-16 of 001).

    Parameters
    ----------
    kernel : {"imq", "tps", "gaussian"}
    affine : bool, optional
        Solve the affine term with the weights (eq. 14). Default True for ``imq`` and
        ``tps``, False for ``gaussian`` (002's formulation, displacement interpolation).
    radius_scale : float
        Multiplies the per-centre radii of eq. (16) (``imq`` only).
    sigma : float, optional
        Gaussian width; default the median nearest-neighbour distance of the centres.
    labels : sequence of str, optional
        Names of the centres, used only in error messages.

    Attributes
    ----------
    centres_ : (n_markers, 3) source points
    radii_ : (n_markers,) per-centre radius (imq) or ``sigma`` repeated (gaussian)
    coef_ : (n_markers + 4, 3) or (n_frames, n_markers + 4, 3)
        RBF weights ``alpha`` then the affine block ``P`` (4 x 3, rows x, y, z, 1);
        the affine block is zero when ``affine`` is False.
    """

    def __init__(self, kernel: str = "imq", affine: bool | None = None, radius_scale: float = 1.0,
                 sigma: float | None = None, labels=None):
        self.kernel = kernel
        self.affine = affine
        self.radius_scale = radius_scale
        self.sigma = sigma
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

    def basis(self, points) -> np.ndarray:
        """The evaluation matrix ``(n_points, n_markers + 4)``: ``f(points) = basis @ coef_``.

        Precompute it once when the same points are mapped for many frames
        (the dense deformer baseline).
        """
        self._check_fitted()
        x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        phi = self._phi(pairwise_distances(x, self.centres_))
        return np.hstack([phi, x, np.ones((len(x), 1))])

    # -- fit / call --------------------------------------------------------------------------
    def fit(self, source, target) -> "RBFRetarget":
        """Solve eq. (14) for ``f(source) = target``.

        Parameters
        ----------
        source : (n_markers, 3) centres (e.g. the neutral frame of the mocap)
        target : (n_markers, 3) or (n_frames, n_markers, 3)

        Raises
        ------
        InputError
            Wrong shapes, NaN markers, fewer than 4 (affine) centres, coincident centres,
            or a degenerate (coplanar) centre set for the affine term.
        """
        if self.kernel not in KERNELS:
            raise InputError(f"kernel: expected one of {', '.join(KERNELS)}, got {self.kernel!r}")
        u = _sanitize_points(source, "source")
        v = _sanitize_points(target, "target", n=len(u), allow_frames=True)
        n = len(u)
        affine = (self.kernel != "gaussian") if self.affine is None else bool(self.affine)
        if n < (4 if affine else 1):
            raise InputError(f"`source`: need at least 4 markers for the affine term, got {n}")
        d = pairwise_distances(u, u)
        scale = float(np.max(d)) if n > 1 else 1.0
        off = d.copy()
        np.fill_diagonal(off, np.inf)
        nn = off.min(axis=1) if n > 1 else np.array([scale])
        if n > 1 and nn.min() <= 1e-9 * max(scale, 1e-300):
            i, j = np.unravel_index(np.argmin(off), off.shape)
            name = (lambda k: f"{k} ({self.labels[k]!r})") if self.labels is not None else str
            raise InputError(f"`source`: centres {name(i)} and {name(j)} coincide (distance {off[i, j]:.3g}); "
                             "an RBF needs distinct centres: drop or merge duplicate markers")
        if self.kernel == "imq":
            self.radii_ = self.radius_scale * nn
        elif self.kernel == "gaussian":
            sigma = float(np.median(nn)) if self.sigma is None else float(self.sigma)
            if not sigma > 0:
                raise InputError(f"sigma: expected a positive width, got {sigma}")
            self.radii_ = np.full(n, sigma)
        else:
            self.radii_ = np.zeros(n)
        self.centres_ = u
        self.affine_ = affine
        phi = self._phi(d)
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
        lu = lu_factor(a, check_finite=False)
        if not np.all(np.isfinite(lu[0])) or np.min(np.abs(np.diag(lu[0]))) < 1e-14 * np.max(np.abs(np.diag(lu[0]))):
            raise InputError(f"`source`: the {self.kernel} system is singular for these centres")
        frames = v.reshape(-1, n, 3)
        rhs = frames if affine else frames - u  # displacement interpolation without the affine term
        if affine:
            rhs = np.concatenate([rhs, np.zeros((len(frames), 4, 3))], axis=1)
        # one factorisation, all frames: columns are (frame, xyz)
        sol = lu_solve(lu, rhs.transpose(1, 0, 2).reshape(len(rhs[0]), -1), check_finite=False)
        sol = sol.reshape(-1, len(frames), 3).transpose(1, 0, 2)
        if not affine:
            coef = np.zeros((len(frames), n + 4, 3))
            coef[:, :n] = sol
            sol = coef
        self.coef_ = sol[0] if v.ndim == 2 else sol
        return self

    def _check_fitted(self):
        if not hasattr(self, "centres_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit(source, target) first")

    def __call__(self, points) -> np.ndarray:
        """Map ``points`` (..., 3); with a multi-frame fit, returns (n_frames, ..., 3)."""
        self._check_fitted()
        x = np.asarray(points, dtype=np.float64)
        if x.shape[-1] != 3:
            raise InputError(f"`points`: expected shape (..., 3), got {x.shape}")
        b = self.basis(x.reshape(-1, 3))
        out = np.einsum("pk,...kc->...pc", b, self.coef_)
        if not self.affine_:
            out = out + x.reshape(-1, 3)
        lead = self.coef_.shape[:-2]
        return out.reshape(lead + x.shape)


MarkerRetarget = RBFRetarget
