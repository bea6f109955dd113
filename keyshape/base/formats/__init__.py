"""One module per file format keyshape reads or writes; algorithm modules never open files."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError


@dataclass(frozen=True)
class Morphs:
    """Morph targets and their take: what the 3D writers (:func:`~keyshape.base.formats.gltf.write_glb`,
    :func:`~keyshape.base.formats.usd.write_usd`) write over a mesh.

    Attributes
    ----------
    deltas : (n_targets, n_vertices, 3) each target minus the base shape
    names : n_targets names
    weights : (n_frames, n_targets) weight of every target at every frame (None: no animation, glTF only)
    fps : the frame rate of the weights and the head motion
    head : :class:`keyshape.retarget.headpose.HeadMotion` (n_frames) or None
    frames : (n_frames,) frame numbers (default ``0..n-1``; glTF's sampler times start at the first one)
    normals : (n_vertices, 3) the base's unit vertex normals (smooth shading), or None
    normal_deltas : (n_targets, n_vertices, 3) each target's normals minus ``normals``, or None
    """

    deltas: np.ndarray
    names: Sequence[str]
    weights: np.ndarray | None = None
    fps: float = 30.0
    head: object = None
    frames: np.ndarray | None = None
    normals: np.ndarray | None = None
    normal_deltas: np.ndarray | None = None

    def checked(self, base: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``(base, deltas, weights, normal_deltas)`` as float64 arrays, checked against each other and against
        ``base`` (n_vertices, 3): a one-line :class:`InputError` for a wrong shape, a non-finite weight, a head
        motion of another length or a frame rate not above 0."""
        base, d = np.asarray(base, dtype=np.float64), np.asarray(self.deltas, dtype=np.float64)
        w = None if self.weights is None else np.asarray(self.weights, dtype=np.float64)
        if base.ndim != 2 or base.shape[1] != 3:
            raise InputError(f"base: expected (n_vertices, 3), got {base.shape}")
        if d.ndim != 3 or d.shape[1:] != base.shape or len(self.names) != len(d):
            raise InputError(f"deltas: expected ({len(self.names)}, {len(base)}, 3), got {d.shape}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"fps must be > 0, got {self.fps}")
        if w is not None and (w.ndim != 2 or w.shape[1] != len(d) or not np.all(np.isfinite(w))):
            raise InputError(f"weights: expected finite (n_frames, {len(d)}), got {w.shape}")
        if self.head is not None and w is not None and self.head.n_frames != len(w):
            raise InputError(f"head motion has {self.head.n_frames} frames, weights {len(w)}")
        nd = None
        if self.normals is not None:
            if np.shape(self.normals) != base.shape:
                raise InputError(f"normals: expected {base.shape}, got {np.shape(self.normals)}")
            if self.normal_deltas is not None:
                nd = np.asarray(self.normal_deltas, dtype=np.float64)
                if nd.shape != d.shape:
                    raise InputError(f"normal deltas: expected {d.shape}, got {nd.shape}")
        return base, d, w, nd
