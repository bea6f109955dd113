"""A rig's curves against a synthetic take's hidden components (bench/rig_accuracy.py and its tests).

``truth.json`` of ``keyshape synth video`` names its 10 hidden components with
ARKit / ICT-FaceKit names; an unsided one (``browInnerUp``) stands for both sides
of a rig that splits it (``browInnerUp_L`` and ``_R``).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.geometry import fit_similarity
from keyshape.retarget.targets.target_set import name_key


def component_columns(rig_names: Sequence[str], component: str) -> list[int]:
    """Rig shape columns standing for ``component`` (one, or both sides of an unsided name)."""
    key = {name_key(n): j for j, n in enumerate(rig_names)}
    k = name_key(component)
    if k in key:
        return [key[k]]
    if k + "left" in key and k + "right" in key:
        return [key[k + "left"], key[k + "right"]]
    raise InputError(f"the rig has no shape for component {component!r}")


def component_gains(neutral: np.ndarray, basis: np.ndarray, components: Sequence[str], rig_names: Sequence[str],
                    rig_neutral: np.ndarray, rig_deltas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How strongly the rig's own shape must be driven to make each hidden component's 2D motion.

    Each component's landmark motion at weight 1, mapped into the rig's frame by the neutral-to-neutral similarity
    (:func:`~keyshape.base.geometry.fit_similarity`), against the projected motion ``r_k`` of its rig shape(s):
    ``gain_k = <m_k, r_k> / <r_k, r_k>`` (least squares) and ``cos_k`` the cosine between the two motions.

    Parameters
    ----------
    neutral : (n_points, 2) the face's neutral landmarks (truth.json ``neutral``)
    basis : (n_components, n_points, 2) each component's landmark motion at weight 1 (truth.json ``basis``)
    components : the components' names
    rig_names : the rig's shape names
    rig_neutral : (n_points, 2) the rig's projected neutral landmarks (:func:`~keyshape.retarget.rig.model.project`)
    rig_deltas : (n_shapes, n_points, 2) projected landmark motion per rig shape

    Returns
    -------
    gains, cos : (n_components,) each
    """
    basis = np.asarray(basis, float)
    sR = fit_similarity(neutral, rig_neutral)[:, :2]
    gains, cos = np.zeros(len(components)), np.zeros(len(components))
    for k, c in enumerate(components):
        m = (basis[k] @ sR.T).ravel()
        r = np.asarray(rig_deltas, float)[component_columns(rig_names, c)].sum(axis=0).ravel()
        rr = float(r @ r)
        if rr < 1e-24 or float(m @ m) < 1e-24:
            raise InputError(f"component {c!r}: no landmark motion in the face or the rig to compare")
        gains[k] = float(m @ r) / rr
        cos[k] = float(m @ r) / np.sqrt(rr * float(m @ m))
    return gains, cos


def truth_curves(rig_names: list, components: list, hidden: np.ndarray) -> np.ndarray:
    """(n_frames, n_shapes) rig curves of the hidden weights (unsided components drive both sides)."""
    out = np.zeros((len(hidden), len(rig_names)))
    for i, c in enumerate(components):
        out[:, component_columns(rig_names, c)] = hidden[:, [i]]
    return out


def score_curves(rig, curves: np.ndarray, components: list, hidden: np.ndarray,
                 vertices: np.ndarray | None = None) -> dict:
    """Pearson r per component (recovered curve, or the mean of both sides, against the hidden weight)
    and the mean vertex error of the rig driven by ``curves`` against the rig driven by the hidden weights,
    with the hidden motion (the rig driven by the hidden weights against the still neutral) for scale."""
    r = {}
    for i, c in enumerate(components):
        rec = curves[:, component_columns(rig.names, c)].mean(axis=1)
        r[c] = float(np.corrcoef(rec, hidden[:, i])[0, 1]) if rec.std() > 0 and hidden[:, i].std() > 0 else 0.0
    truth = truth_curves(rig.names, components, hidden)
    err = motion = 0.0
    for s in range(0, len(curves), 100):                          # chunks: bounded memory
        vt = rig.evaluate(truth[s:s + 100], vertices)
        vr = rig.evaluate(curves[s:s + 100], vertices)
        n0 = rig.neutral if vertices is None else rig.neutral[vertices]
        err += np.linalg.norm(vr - vt, axis=2).mean(axis=1).sum()
        motion += np.linalg.norm(vt - n0, axis=2).mean(axis=1).sum()
    return {"r": r, "mean_r": float(np.mean(list(r.values()))), "vertex_error": err / len(curves),
            "hidden_motion": motion / len(curves), "error_ratio": err / max(motion, 1e-12)}
