"""Key-shape selectors (section 4.2 of 004_119ba07521a9af0b.txt) with one estimator interface.

Design notes and figures: docs/decompose.md, "Notes on the code", ``decompose/selectors.py``.
"""
from __future__ import annotations

import hashlib
import threading

import numpy as np

from keyshape.base.errors import InputError, NotFittedError
from keyshape.base.progress import Progress
from keyshape.decompose.defaults import METHODS  # noqa: F401  (the selectors' names, defined in one place)
from keyshape.decompose.weights import nnls_gram


def _check_shapes(shapes, n_keys: int | None) -> np.ndarray:
    arr = np.asarray(shapes, dtype=np.float64)
    if arr.ndim != 3:
        raise InputError(f"shapes: expected (n_frames, n_points, dim), got shape {arr.shape}")
    if not np.isfinite(arr).all():
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=(1, 2)))
        raise InputError(f"shapes contain NaN at frame rows {bad[:5].tolist()}: exclude failed frames "
                         f"before selecting key shapes")
    if n_keys is not None:
        if int(n_keys) < 1:
            raise InputError(f"n_keys must be at least 1, got {n_keys}")
        if n_keys > len(arr):
            raise InputError(f"cannot choose {n_keys} key shapes from {len(arr)} frames "
                             f"(k larger than the frames available)")
    return arr


_PCA_CACHE: dict = {}   # the last few PCA scores, keyed by the data's shape and hash
_PCA_LOCK = threading.Lock()   # selectors may be fitted on several threads (keyshape batch with thread workers)


def _pca(X: np.ndarray) -> np.ndarray:
    """PCA scores (n_frames, r) of ``X`` (scikit-learn's exact PCA), r the numerical rank.

    Each axis' sign is fixed so that its largest-magnitude score is positive (the
    frame-side ``svd_flip`` convention), so the order of spread's picks does not
    depend on the library's sign convention.
    """
    from sklearn.decomposition import PCA

    if len(X) < 2 or not np.abs(X - X.mean(0)).max() > 0:
        return np.zeros((len(X), 0))
    key = (X.shape, hashlib.blake2b(np.ascontiguousarray(X).view(np.uint8), digest_size=16).digest())
    with _PCA_LOCK:
        if key in _PCA_CACHE:                    # keyshape compare fits many selectors to one region
            return _PCA_CACHE[key].copy()
    pca = PCA(svd_solver="full").fit(X)
    s = pca.singular_values_
    r = int((s > s[0] * 1e-10).sum())
    scores = pca.transform(X)[:, :r]
    signs = np.sign(scores[np.argmax(np.abs(scores), axis=0), np.arange(r)])
    signs[signs == 0] = 1
    scores = scores * signs
    with _PCA_LOCK:
        if len(_PCA_CACHE) >= 4 and key not in _PCA_CACHE:
            _PCA_CACHE.pop(next(iter(_PCA_CACHE)))
        _PCA_CACHE[key] = scores
    return scores.copy()


class _Selector:
    """Shared fit scaffolding: validate, centre on the mean, learn, set keys."""

    def __init__(self, n_keys: int = 8):
        self.n_keys = n_keys

    def fit(self, shapes: np.ndarray, neutral: np.ndarray | None = None) -> "_Selector":
        """Choose key shapes from ``shapes`` (n_frames, n_points, dim); returns ``self``.

        ``neutral`` (n_points, dim): the shape the keys and weights are relative to
        (default: the mean shape, the paper's centring; the actor's neutral frame makes
        the NNLS cone start at the relaxed face)."""
        arr = _check_shapes(shapes, self.n_keys)
        self.neutral_ = arr.mean(axis=0) if neutral is None else np.asarray(neutral, dtype=np.float64)
        X = (arr - self.neutral_).reshape(len(arr), -1)
        idx, keys = self._select(X, arr)
        self.indices_ = np.asarray(idx, dtype=np.intp)
        self.keys_ = arr[self.indices_].copy() if keys is None else keys
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "indices_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit(shapes) first")

    @property
    def n_keys_(self) -> int:
        self._check_fitted()
        return len(self.indices_)

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if not k.endswith("_"))
        return f"{type(self).__name__}({params})"


class SpreadSelector(_Selector):
    """Maximum spread along principal components (the paper's method, section 4.2).

    PCA of the mean-centred shapes; for axis 0, 1, ... the frames with the maximum
    and then the minimum projection are chosen, skipping frames already chosen,
    until ``n_keys`` are chosen (the first ``ceil(k/2)`` axes; the last contributes
    only its maximum when k is odd). If the axes run out (rank < k/2), the pass is
    repeated taking each axis' next-most-extreme frames. ``order_`` is nested:
    the first j keys of a fit with k are those of a fit with j.
    """

    def _select(self, X, arr):
        scores = _pca(X)
        if scores.shape[1] == 0:
            raise InputError("all shapes are identical: there is no variation to choose key shapes from")
        order_max = np.argsort(-scores, axis=0, kind="stable")
        order_min = np.argsort(scores, axis=0, kind="stable")
        chosen: list[int] = []
        taken = np.zeros(len(X), dtype=bool)
        depth = np.zeros((scores.shape[1], 2), dtype=np.intp)
        while len(chosen) < self.n_keys:
            progress = False
            for a in range(scores.shape[1]):
                for side, order in ((0, order_max), (1, order_min)):
                    if len(chosen) == self.n_keys:
                        break
                    d = depth[a, side]
                    while d < len(X) and taken[order[d, a]]:
                        d += 1
                    depth[a, side] = d + 1
                    if d < len(X):
                        chosen.append(int(order[d, a]))
                        taken[order[d, a]] = True
                        progress = True
            if not progress:
                break
        self.order_ = np.array(chosen, dtype=np.intp)
        return chosen, None


class KMeansSelector(_Selector):
    """k-means clustering of the first ``n_dims`` PCA coordinates (section 4.2, "Clustering").

    Parameters
    ----------
    n_keys : int
    n_dims : int
        PCA coordinates clustered (the paper reports 2 and 3).
    centre : {"mean", "nearest"}
        ``"mean"``: the key shape is the cluster's centre of mass in shape space (as the
        paper says); ``indices_`` then holds the frame nearest each centre, for display.
        ``"nearest"``: the key is that nearest frame itself.
    rng : None, int or Generator
        Seeds the k-means initialisations (scikit-learn's ``KMeans``, k-means++, best of 4).
    """

    def __init__(self, n_keys: int = 8, n_dims: int = 2, centre: str = "mean", rng=None):
        self.n_keys = n_keys
        self.n_dims = n_dims
        self.centre = centre
        self.rng = rng

    def _select(self, X, arr):
        if self.centre not in ("mean", "nearest"):
            raise InputError(f"centre must be 'mean' or 'nearest', got {self.centre!r}")
        scores = _pca(X)
        Y = scores[:, :self.n_dims]
        n_distinct = len(np.unique(Y.round(12), axis=0))
        if n_distinct < self.n_keys:
            raise InputError(f"cannot form {self.n_keys} clusters from {n_distinct} distinct shapes")
        from sklearn.cluster import KMeans

        seed = int(np.random.default_rng(self.rng).integers(2**31 - 1))
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1):   # tiny problems: OpenMP threads only spin (3x the CPU time on 2 cores)
            labels = KMeans(self.n_keys, init="k-means++", n_init=4, max_iter=100,
                            random_state=seed).fit_predict(Y)
        counts = np.bincount(labels, minlength=self.n_keys)
        centres = np.einsum("tc,tpd->cpd", np.eye(self.n_keys)[labels], arr) / counts[:, None, None]
        d2 = ((X[None] - (centres - self.neutral_).reshape(self.n_keys, 1, -1)) ** 2).sum(-1)
        d2[labels[None] != np.arange(self.n_keys)[:, None]] = np.inf  # nearest member of its own cluster
        idx = np.argmin(d2, axis=1)
        return idx, (centres if self.centre == "mean" else None)


class HullSelector(_Selector):
    """Frames on the 2D convex hull of the first two PCA coordinates (section 4.2, "Convex hull"): every frame on
    the hull is a key, however many that is."""

    def __init__(self):
        self.n_keys = None

    def _select(self, X, arr):
        from scipy.spatial import ConvexHull, QhullError

        scores = _pca(X)
        if scores.shape[1] < 2:
            raise InputError("the shapes vary along fewer than two directions: no 2D hull")
        try:
            hull = ConvexHull(scores[:, :2])
        except QhullError as exc:
            raise InputError(f"convex hull failed ({str(exc).splitlines()[0]})") from None
        return hull.vertices, None


class RandomSelector(_Selector):
    """``n_keys`` distinct frames drawn at random (the baseline); ``rng``: None, int or Generator."""

    def __init__(self, n_keys: int = 8, rng=None):
        self.n_keys = n_keys
        self.rng = rng

    def _select(self, X, arr):
        return np.random.default_rng(self.rng).choice(len(X), size=self.n_keys, replace=False), None


class GreedySelector(_Selector):
    """Greedy forward selection on the NNLS reconstruction error itself (this toolkit's own).

    Each step adds the frame whose addition most reduces eq. (5),
    ``E = sum_t min_{w_t >= 0} ||Q_t - neutral - sum_i w_ti (S_i - neutral)||^2``, evaluated exactly on a shortlist:
    the ``n_candidates`` frames that most reduce the least-squares residual (gain ``||R c_perp||^2 / ||c_perp||^2``)
    and the ``n_candidates`` frames worst reconstructed now, all candidates' NNLS problems solved together
    (:func:`~decompose.weights.nnls_gram`); on long takes on ``max_eval`` frames drawn with ``rng``. ``order_`` is
    nested: the first j keys of a fit with k are the fit with j.
    """

    def __init__(self, n_keys: int = 8, n_candidates: int = 10, max_eval: int = 1500, rng=None,
                 progress: bool = False, desc: str = "greedy"):
        self.n_keys = n_keys
        self.n_candidates = n_candidates
        self.max_eval = max_eval
        self.rng = rng
        self.progress = progress
        self.desc = desc

    def _select(self, X, arr):
        n = len(X)
        rng = np.random.default_rng(self.rng)
        ev = np.sort(rng.choice(n, self.max_eval, replace=False)) if n > self.max_eval else np.arange(n)
        E = X[ev]                                     # evaluation frames (n_eval, d)
        sq = (X ** 2).sum(axis=1)
        chosen: list[int] = []
        resid_nnls = (E ** 2).sum(axis=1)             # per evaluation frame, current NNLS residual
        Q = np.zeros((0, X.shape[1]))                 # orthonormal basis of the chosen keys' span
        w_prev = np.zeros((len(E), 0))
        prog = Progress(self.n_keys, desc=self.desc, unit="keys", enabled=self.progress, min_seconds=2.0)
        for _ in range(self.n_keys):
            R = E - (E @ Q.T) @ Q                     # least-squares residuals
            C = X - (X @ Q.T) @ Q                     # candidates' parts outside the span
            cn = (C ** 2).sum(axis=1)
            ok = cn > 1e-12 * max(sq.max(), 1e-300)
            ok[chosen] = False
            if not ok.any():
                ok = np.ones(n, dtype=bool)
                ok[chosen] = False
            gain = np.where(ok, ((R @ C.T) ** 2).sum(axis=0) / np.where(ok, cn, 1.0), -np.inf)
            short = set(np.argsort(-gain)[:self.n_candidates].tolist())
            worst = ev[np.argsort(-resid_nnls)]
            short.update([int(i) for i in worst if ok[i]][:self.n_candidates])
            cands = np.array(sorted(short), dtype=np.intp)
            errs, res, w_best = self._nnls_errors(E, X, chosen, cands, w_prev)
            best = int(np.argmin(errs))
            c = int(cands[best])
            chosen.append(c)
            resid_nnls = res[best]
            w_prev = w_best[best]
            q = C[c] / np.sqrt(cn[c]) if cn[c] > 0 else np.zeros(X.shape[1])
            Q = np.vstack([Q, q])
            prog.update()
        prog.close()
        self.order_ = np.array(chosen, dtype=np.intp)
        return chosen, None

    @staticmethod
    def _nnls_errors(E, X, chosen, cands, w_prev):
        """Eq. (5) over the evaluation frames for keys ``chosen + [c]``, all candidates c in one batch.

        One NNLS problem per (candidate, frame) pair, solved together; warm-started
        from the previous step's weights (the new key's weight starts positive).
        """
        B0 = X[chosen]                                  # (j, d)
        Bc = X[cands]                                   # (m, d)
        j, m, ne = len(chosen), len(cands), len(E)
        G = np.empty((m, j + 1, j + 1))
        G[:, :j, :j] = B0 @ B0.T
        G[:, :j, j] = G[:, j, :j] = Bc @ B0.T
        G[:, j, j] = (Bc ** 2).sum(axis=1)
        h = np.empty((m, ne, j + 1))
        h[:, :, :j] = E @ B0.T
        h[:, :, j] = (E @ Bc.T).T
        passive = np.ones((m, ne, j + 1), dtype=bool)
        passive[:, :, :j] = w_prev > 0
        Gr = np.broadcast_to(G[:, None], (m, ne, j + 1, j + 1)).reshape(m * ne, j + 1, j + 1)
        w, _ = nnls_gram(Gr, h.reshape(m * ne, j + 1), passive=passive.reshape(m * ne, j + 1))
        w = w.reshape(m, ne, j + 1)
        e2 = (E ** 2).sum(axis=1)
        r = e2 - 2 * (w * h).sum(-1) + np.einsum("mti,mij,mtj->mt", w, G, w)
        res = np.maximum(r, 0.0)
        return res.sum(axis=1), res, w


def make_selector(method: str, n_keys: int, rng=None, progress: bool = False, desc: str = "greedy") -> _Selector:
    """The selector named ``method`` (one of :data:`METHODS`) for ``n_keys`` keys (``progress``:
    report the keys chosen so far on standard error, for the slow greedy selector)."""
    if method == "spread":
        return SpreadSelector(n_keys)
    if method in ("kmeans2", "kmeans3"):
        return KMeansSelector(n_keys, n_dims=int(method[-1]), rng=rng)
    if method == "hull2":
        return HullSelector()                   # the whole hull, whatever n_keys (the paper's method)
    if method == "random":
        return RandomSelector(n_keys, rng=rng)
    if method == "greedy":
        return GreedySelector(n_keys, rng=rng, progress=progress, desc=desc)
    raise InputError(f"unknown selection method {method!r}: use one of {', '.join(METHODS)}")
