"""The retargeting stage as one object: target key shapes (+ regions) fitted once, any weights evaluated.

Section 5 of 004_119ba07521a9af0b.txt: the weights found on the source key
shapes are kept and only the key shapes are replaced by the artist's targets;
with face regions, each region's targets are blended with its own weights and
the regions are blended with per-vertex weights that fall off across a band.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError, NotFittedError
from keyshape.retarget.targets.blend import BlendBasis, _check_weights, mesh_edges, region_weights
from keyshape.retarget.targets.target_set import TargetSet, key_regions


class Retargeter:
    """Blend a :class:`~retarget.targets.target_set.TargetSet` with per-frame key-shape weights.

    Parameters
    ----------
    form : {"auto", "absolute", "delta"}
        ``sum_i w_i B_i`` (the paper's literal Eq. 2) or ``N + sum_i w_i (B_i - N)``; "auto"
        (default) is "delta" when the targets have a neutral, else "absolute" (see
        :mod:`keyshape.retarget.targets.blend`: use the form the weights were fitted in).
    band : float or None
        Width of the region blending band in mesh units (default: 10% of the mesh's
        bounding-box diagonal).
    metric : {"geodesic", "euclidean"}
        Distance used for the band (geodesic needs mesh faces; falls back to
        euclidean for 2D targets).
    dtype : dtype of the evaluated frames.

    Attributes
    ----------
    form_ : "absolute" or "delta", the form used
    targets_ : TargetSet
    region_names_ : list of region names or None
    key_regions_ : (n_keys,) region index per key shape or None
    region_weights_ : (n_regions, n_vertices) or None
    basis_ : BlendBasis
    """

    def __init__(self, form: str = "auto", band: float | None = None, metric: str = "geodesic",
                 dtype=np.float64):
        self.form, self.band, self.metric, self.dtype = form, band, metric, dtype

    def fit(self, targets: TargetSet, regions: dict[str, np.ndarray] | None = None,
            regions_source: str = "regions") -> "Retargeter":
        """Precompute the blend basis (regions folded in, see :class:`~retarget.targets.blend.BlendBasis`)."""
        self.targets_ = targets
        self.region_names_ = self.key_regions_ = self.region_weights_ = None
        if regions:
            names, kr = key_regions(targets.columns, regions, regions_source)
            ref = targets.neutral if targets.neutral is not None else targets.shapes[0]
            band = self.band
            if band is None:
                band = 0.1 * float(np.linalg.norm(ref.max(axis=0) - ref.min(axis=0)))
            edges = None
            metric = self.metric
            if metric == "geodesic":
                if targets.mesh is None or not targets.mesh.polygons:
                    metric = "euclidean"
                else:
                    edges = mesh_edges(targets.mesh.polygons)
            self.region_weights_ = region_weights(ref, [regions[n] for n in names], band, edges, metric)
            self.region_names_, self.key_regions_ = names, kr
        self.basis_ = BlendBasis(self.form, self.dtype).fit(targets.shapes, targets.neutral, self.key_regions_,
                                                           self.region_weights_)
        self.form_ = self.basis_.form_
        return self

    def _fitted(self):
        if not hasattr(self, "basis_"):
            raise NotFittedError("Retargeter is not fitted: call fit(targets) first")

    def transform(self, weights: np.ndarray, out: np.ndarray | None = None,
                  chunk_frames: int | None = None) -> np.ndarray:
        """Retargeted frames ``(n_frames, n_vertices, dim)``: one matrix product over all frames."""
        self._fitted()
        return self.basis_.transform(weights, out=out, chunk_frames=chunk_frames)

    def morph_targets(self, weights: np.ndarray, clamp: bool = False):
        """Exact glTF morph targets and weights for these weights.

        glTF evaluates ``base + sum_j m_j D_j``. With per-key region scaling ``R_i(v)``:

        * delta form: ``base = N``, ``D_i = R_i (B_i - N)``, ``m_i = w_i``;
        * absolute form: ``sum_r a_r sum_{i in r} w_i B_i
          = base + sum_i w_i R_i (B_i - base) + sum_r (S_r - 1) a_r base`` with
          ``S_r = sum_{i in r} w_i``: one extra target ``keyshape_sum[_region]`` per region,
          ``D = a_r base`` with weight ``S_r - 1``, added only when some ``|S_r - 1| > 1e-6``
          (NNLS weights rarely sum to one exactly).

        Returns
        -------
        base : (n_vertices, 3), deltas : (n_morph, n_vertices, 3), names : list, morph_weights :
        (n_frames, n_morph), n_clamped : int (weights changed by ``clamp``)
        """
        self._fitted()
        ts = self.targets_
        if ts.dim != 3:
            raise InputError("glTF output needs 3D (OBJ) targets; these are 2D drawings")
        w, n_clamped = clamp_weights(_check_weights(weights, len(ts.columns)).astype(np.float64), clamp)
        base = ts.neutral if ts.neutral is not None else ts.shapes[0]
        if self.region_weights_ is None:
            rw, kr, rnames = np.ones((1, ts.n_vertices)), np.zeros(len(ts.columns), np.intp), [None]
        else:
            rw, kr, rnames = self.region_weights_, self.key_regions_, self.region_names_
        deltas = rw[kr][:, :, None] * (ts.shapes - base)
        names = _unique(ts.names, ts.columns)
        mw = w
        if self.form_ == "absolute":
            sums = np.stack([w[:, kr == r].sum(axis=1) for r in range(len(rw))], axis=1) - 1.0
            if np.any(np.abs(sums) > 1e-6):
                deltas = np.concatenate([deltas, rw[:, :, None] * base[None]])
                names = names + ["keyshape_sum" + ("" if r is None else f"_{r}") for r in rnames]
                mw = np.concatenate([w, sums], axis=1)
        return base, deltas, names, mw, n_clamped


def clamp_weights(weights: np.ndarray, clamp: bool = True) -> tuple[np.ndarray, int]:
    """``weights`` clipped to [0, 1] where ``clamp`` (glTF and ARKit consumers' range), and how many values changed."""
    if not clamp:
        return weights, 0
    c = np.clip(weights, 0.0, 1.0)
    return c, int(np.count_nonzero(c != weights))


def _unique(names: Sequence[str], columns: Sequence[str]) -> list[str]:
    return [n if list(names).count(n) == 1 else f"{n}_{c}" for n, c in zip(names, columns)]
