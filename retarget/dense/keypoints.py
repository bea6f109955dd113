"""Automatic key-point insertion for dense sequences (section 5 of 002_dce09d5f5656b088.txt).

Design notes and figures: docs/keypoints.md, "Notes on the code", ``retarget/dense/keypoints.py``.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from keyshape.base.errors import InputError, NotFittedError
from keyshape.retarget.rbf import RBF


def check_sequence(frames: np.ndarray, name: str = "frames") -> np.ndarray:
    """Validate a dense sequence (n_frames, n_points, 3) and return it as float64."""
    f = np.asarray(frames, dtype=np.float64)
    if f.ndim != 3 or f.shape[2] != 3 or f.shape[0] < 2 or f.shape[1] < 4:
        raise InputError(f"{name}: expected (n_frames >= 2, n_points >= 4, 3), got {f.shape}")
    if not np.all(np.isfinite(f)):
        raise InputError(f"{name}: contains NaN or infinite values")
    return f


def farthest_point_sample(points: np.ndarray, k: int, rng=None) -> np.ndarray:
    """``k`` indices of ``points`` spread by farthest-point sampling from a seeded start."""
    rng = np.random.default_rng(rng)
    n = len(points)
    if not 1 <= k <= n:
        raise InputError(f"cannot pick {k} points from {n}")
    idx = np.empty(k, np.intp)
    idx[0] = rng.integers(n)
    d = np.linalg.norm(points - points[idx[0]], axis=1)
    for i in range(1, k):
        idx[i] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(points - points[idx[i]], axis=1))
    return idx


def surface_errors(deformed: np.ndarray, trees: list) -> np.ndarray:
    """(n_frames, n_points) distance from each deformed point to the nearest point of ``F^t``."""
    return np.stack([tree.query(d)[0] for d, tree in zip(deformed, trees)])


def _neighbours(tree0: cKDTree, centres: np.ndarray, radius: float) -> csr_matrix:
    """Sparse (n_centres, n_points) indicator of rest points within ``radius`` of each centre."""
    lists = tree0.query_ball_point(centres, radius)
    lens = np.fromiter((len(l) for l in lists), np.intp, len(lists))
    cols = np.fromiter((j for l in lists for j in l), np.intp, int(lens.sum()))
    rows = np.repeat(np.arange(len(lists)), lens)
    return csr_matrix((np.ones(len(cols)), (rows, cols)), shape=(len(centres), tree0.n))


def refine_positions(rest: np.ndarray, deformed: np.ndarray, trees: list, indices: np.ndarray,
                     radius: float, n_iter: int = 8) -> np.ndarray:
    """Per-frame positions (n_frames, len(indices), 3) of rest vertices ``indices`` (section 5.4).

    For each new key point ``k`` the currently tracked surface patch (rest
    points within ``radius`` of ``k``, deformed to frame ``t``) is registered
    non-rigidly onto ``F^t``: ``n_iter`` rounds of closest points, with the
    residuals (closest points farther than ``2 radius`` from the key point
    are dropped, the paper's 2R sphere) smoothed by a Gaussian of width
    ``radius / 2`` over the patch, give a displacement field; the key point
    moves with its patch. All patches and frames are processed as padded
    arrays: one nearest-point query per frame and iteration.
    """
    indices = np.asarray(indices, np.intp)
    if len(indices) == 0:
        return np.zeros((len(deformed), 0, 3))
    tree0 = cKDTree(rest)
    lists = tree0.query_ball_point(rest[indices], radius)
    size = max(len(l) for l in lists)
    patch = np.zeros((len(indices), size), np.intp)
    valid = np.zeros((len(indices), size), bool)
    for i, l in enumerate(lists):  # once per new key point, not per frame
        patch[i, :len(l)] = l
        valid[i, :len(l)] = True
    d0 = np.linalg.norm(rest[patch] - rest[indices][:, None], axis=2)
    w_centre = np.exp(-0.5 * (d0 / (0.5 * radius)) ** 2) * valid  # (n_new, size)
    pts = deformed[:, patch].copy()  # (n_frames, n_new, size, 3)
    centre = deformed[:, indices].copy()
    for _ in range(n_iter):
        for t, tree in enumerate(trees):
            dist, j = tree.query(pts[t].reshape(-1, 3))
            q = tree.data[j].reshape(pts[t].shape)
            ok = valid & (np.linalg.norm(q - centre[t][:, None], axis=2) < 2 * radius)
            w = w_centre * ok
            u = np.einsum("ns,nsd->nd", w, q - pts[t]) / np.maximum(w.sum(1), 1e-12)[:, None]
            pts[t] += u[:, None]
            centre[t] += u
    return centre



def face_rbf(sigma: float | None, smoothing: float) -> RBF:
    """The face-space deformation of 002 section 4: a Gaussian RBF interpolating displacements,
    sigma 1.25 x the keys' median nearest-neighbour distance unless given."""
    return RBF("gaussian", affine=False, sigma=sigma, sigma_scale=1.25, smoothing=smoothing)

class KeyPointInserter:
    """Insert key points where the face-space deformation fails (section 5 of 002).

    Parameters
    ----------
    radius : float, optional
        Neighbourhood radius ``R`` (mesh units) of the candidate tests and of
        the refinement. Default: 2 % of the rest face's bounding-box diagonal.
    n_candidates : int
        Rest points sampled at random as candidates each round (paper: 4000).
    max_new : int
        At most this many key points added per round (paper: under 40).
    threshold : float, optional
        Neighbourhood error sum a candidate must exceed (condition 1 of 5.2).
        Default: the median of the sampled candidates' neighbourhood sums.
    tol : float
        Stop when a round lowers the mean error by less than this fraction (5.5).
    max_rounds : int
    sigma, smoothing : float, optional
        RBF width and ridge (see :func:`face_rbf`); sigma defaults to the initial keys' spacing and
        stays fixed over the rounds (the paper's fixed sigma).
    correspondence : bool
        True (default): the points of every frame correspond to the rest
        points (a tracked mesh, as SEQUENCE.npz holds): the error is the
        distance to the same point in ``F^t`` and a new key point's
        positions are read from ``F^t``. False: the paper's setting of
        unregistered scans: nearest-point errors and per-frame placement
        by local non-rigid registration (5.4).
    temporal_filter, refine : bool
        Switch off section 5.3 / 5.4 (for ablations; both on in the paper).
    rng : None, int or Generator

    Attributes
    ----------
    key_indices_ : (n_keys,) rest-vertex index of each key point
    key_positions_ : (n_frames, n_keys, 3) key-point positions per frame
    history_ : list of dicts per round (mean error, n_keys, added, removed)
    sigma_ : the kernel width used
    """

    def __init__(self, radius: float | None = None, n_candidates: int = 4000, max_new: int = 40,
                 threshold: float | None = None, tol: float = 0.01, max_rounds: int = 8,
                 sigma: float | None = None, smoothing: float = 1e-2, correspondence: bool = True,
                 temporal_filter: bool = True, refine: bool = True, rng=None):
        self.radius = radius
        self.n_candidates = n_candidates
        self.max_new = max_new
        self.threshold = threshold
        self.tol = tol
        self.max_rounds = max_rounds
        self.sigma = sigma
        self.smoothing = smoothing
        self.correspondence = correspondence
        self.temporal_filter = temporal_filter
        self.refine = refine
        self.rng = rng

    # -- pieces -------------------------------------------------------------
    def _setup(self, frames, initial, positions):
        frames = check_sequence(frames)
        initial = np.asarray(initial)
        if initial.ndim != 1 or initial.dtype.kind not in "iu" or len(initial) < 1:
            raise InputError(f"initial key points: expected a 1-D array of vertex indices, got {initial!r:.80}")
        if initial.min() < 0 or initial.max() >= frames.shape[1]:
            raise InputError(f"initial key points: indices must lie in 0..{frames.shape[1] - 1}, "
                             f"got {initial.min()}..{initial.max()}")
        if len(np.unique(initial)) != len(initial):
            raise InputError("initial key points: repeated vertex index")
        if positions is None:
            positions = frames[:, initial]
        positions = np.asarray(positions, np.float64)
        if positions.shape != (frames.shape[0], len(initial), 3):
            raise InputError(f"initial key positions: expected {(frames.shape[0], len(initial), 3)}, "
                             f"got {positions.shape}")
        return frames, initial.astype(np.intp), positions

    def _radius(self, rest):
        if self.radius is not None:
            return float(self.radius)
        return 0.02 * float(np.linalg.norm(rest.max(0) - rest.min(0)))

    def deform(self, frames: np.ndarray, indices: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """``D(F^0 -> F^t)`` for every frame: (n_frames, n_points, 3) (eq. 4)."""
        rest = frames[0]
        rbf = face_rbf(getattr(self, "sigma_", self.sigma), self.smoothing).fit(rest[indices])
        return rbf.deform(rest, positions)

    def _candidates(self, rest, err_t, tree0, radius, rng):
        """Sections 5.2-5.3: sampled rest indices that pass the local-maximum, threshold and temporal tests."""
        err = err_t.mean(0)
        n = len(rest)
        cand = rng.choice(n, size=min(self.n_candidates, n), replace=False)
        nb = _neighbours(tree0, rest[cand], radius)
        nsum = nb @ err
        # local maximum: error of the candidate >= every neighbour's
        # (condition 2) the candidate's error is the largest among the sampled candidates around it
        cand_nb = _neighbours(cKDTree(rest[cand]), rest[cand], radius)
        nb_max = cand_nb.multiply(err[cand][None, :]).max(axis=1).toarray().ravel()
        thr = np.median(nsum) if self.threshold is None else self.threshold
        keep = (nsum > thr) & (err[cand] >= nb_max - 1e-15) & (err[cand] > 0)
        cand, nb = cand[keep], nb[keep]
        if len(cand) == 0:
            return cand
        if self.temporal_filter:
            # correlation over frames between the candidate's error and each neighbour's, averaged
            z = err_t - err_t.mean(0)
            z = z / np.maximum(np.linalg.norm(z, axis=0), 1e-15)
            corr_sum = np.asarray(nb.multiply(z[:, cand].T @ z).sum(axis=1)).ravel()
            n_nb = np.asarray(nb.sum(axis=1)).ravel()
            corr = (corr_sum - 1.0) / np.maximum(n_nb - 1, 1)  # exclude the candidate itself
            good = corr >= corr.mean()
            cand = cand[good]
        order = np.argsort(-err[cand], kind="stable")
        # greedy spacing: no two new keys within R
        chosen = []
        for c in cand[order]:  # at most a few hundred candidates, once per round
            if all(np.linalg.norm(rest[c] - rest[o]) >= radius for o in chosen):
                chosen.append(c)
            if len(chosen) >= self.max_new:
                break
        return np.array(chosen, np.intp)

    # -- estimator ------------------------------------------------------------
    def fit(self, frames: np.ndarray, initial: np.ndarray, positions: np.ndarray | None = None) -> "KeyPointInserter":
        """Insert key points into the sequence ``frames`` starting from rest indices ``initial``.

        ``positions`` (n_frames, n_initial, 3) gives the initial key points'
        tracked positions; default ``frames[:, initial]`` (the points
        correspond over frames, as in the synthetic data).
        """
        frames, idx, pos = self._setup(frames, initial, positions)
        rng = np.random.default_rng(self.rng)
        rest = frames[0]
        radius = self._radius(rest)
        tree0 = cKDTree(rest)
        # one fixed kernel width for every round (section 4.1.1), from the initial keys unless given
        self.sigma_ = face_rbf(self.sigma, self.smoothing).fit(rest[idx]).sigma_
        if self.correspondence:
            trees = None
            def errors(d):
                return np.linalg.norm(d - frames, axis=2)
        else:
            trees = [cKDTree(f) for f in frames]
            def errors(d):
                return surface_errors(d, trees)
        deformed = self.deform(frames, idx, pos)
        err_t = errors(deformed)
        history = [dict(round=0, mean_error=float(err_t.mean()), n_keys=len(idx), added=0, removed=0)]
        for r in range(1, self.max_rounds + 1):
            new = self._candidates(rest, err_t, tree0, radius, rng)
            new = new[~np.isin(new, idx)]
            if len(new) == 0:
                break
            if self.correspondence:
                new_pos = frames[:, new]
                # 5.5: drop old key points whose own tracking error exceeds the worst new one's
                key_err = np.linalg.norm(np.concatenate([pos, new_pos], 1) - frames[:, np.concatenate([idx, new])],
                                         axis=2).mean(0)
            else:
                new_pos = refine_positions(rest, deformed, trees, new, radius) if self.refine else deformed[:, new]
                key_err = surface_errors(np.concatenate([pos, new_pos], 1), trees).mean(0)
            worst_new = key_err[len(idx):].max()
            drop = key_err[:len(idx)] > worst_new
            prev = history[-1]["mean_error"]
            # candidates come ordered by error: if the round does not help, retry with the better half
            while True:
                cand_idx = np.concatenate([idx[~drop], new])
                cand_pos = np.concatenate([pos[:, ~drop], new_pos], 1)
                cand_def = self.deform(frames, cand_idx, cand_pos)
                cand_err = errors(cand_def)
                cur = float(cand_err.mean())
                if cur < prev or len(new) == 1:
                    break
                new, new_pos = new[:len(new) // 2], new_pos[:, :len(new) // 2]
            if cur >= prev:
                break
            idx, pos, deformed, err_t = cand_idx, cand_pos, cand_def, cand_err
            history.append(dict(round=r, mean_error=cur, n_keys=len(idx), added=int(len(new)),
                                removed=int(drop.sum())))
            if (prev - cur) / prev < self.tol:
                break
        self.key_indices_ = idx
        self.key_positions_ = pos
        self.history_ = history
        self.radius_ = radius
        return self

    def _check_fitted(self):
        if not hasattr(self, "key_indices_"):
            raise NotFittedError("KeyPointInserter is not fitted: call fit(frames, initial) first")

    def reconstruct(self, frames: np.ndarray) -> np.ndarray:
        """The sequence rebuilt from ``frames[0]`` and the fitted key points: (n_frames, n_points, 3)."""
        self._check_fitted()
        frames = check_sequence(frames)
        return self.deform(frames, self.key_indices_, self.key_positions_)


def random_insertion(frames: np.ndarray, initial: np.ndarray, n_new: int, radius: float, rng=None,
                     correspondence: bool = True, sigma: float | None = None, smoothing: float = 1e-2) -> tuple[np.ndarray, np.ndarray]:
    """Baseline of Table 2: ``n_new`` random rest points added, placed by the same refinement.

    Positions of the new points are read from ``frames`` (``correspondence``)
    or found by :func:`refine_positions`. Returns (indices, positions (n_frames, n_keys, 3)).
    """
    frames = check_sequence(frames)
    rng = np.random.default_rng(rng)
    initial = np.asarray(initial, np.intp)
    pool = np.setdiff1d(np.arange(frames.shape[1]), initial)
    new = rng.choice(pool, size=n_new, replace=False)
    if correspondence:
        new_pos = frames[:, new]
    else:
        trees = [cKDTree(f) for f in frames]
        rest = frames[0]
        deformed = face_rbf(sigma, smoothing).fit(rest[initial]).deform(rest, frames[:, initial])
        new_pos = refine_positions(rest, deformed, trees, new, radius)
    return np.concatenate([initial, new]), np.concatenate([frames[:, initial], new_pos], 1)


def sequence_errors(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray | None = None) -> dict:
    """Mean error and RMSE of per-point distances (Table 1's columns), over ``points`` (default all)."""
    d = np.linalg.norm(estimate - truth, axis=-1)
    if points is not None:
        d = d[:, points]
    return dict(mean=float(d.mean()), rmse=float(np.sqrt((d ** 2).mean())))
