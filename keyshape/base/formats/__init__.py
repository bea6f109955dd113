"""One module per file format keyshape reads or writes; algorithm modules never open files."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


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
