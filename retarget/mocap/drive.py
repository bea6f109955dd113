"""The marker path end to end: a cleaned take drives a dense target mesh (001 sections 4-5).

Design notes and figures: docs/mocap.md, "Notes on the code", ``retarget/mocap/drive.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from keyshape.base.errors import InputError
from keyshape.retarget.mocap.clean import GapReport, fill_gaps, rebuild_inner_lips, remove_rigid_motion
from keyshape.retarget.mocap.planar_bones import PlanarBones
from keyshape.retarget.rbf import RBF
from keyshape.retarget.mocap.triangulate import Triangulation, triangulate_markers

METHODS = ("planar", "imq", "tps", "gaussian")


@dataclass
class DriveResult:
    """Per-frame dense meshes and what was done to get them."""

    vertices: np.ndarray                 # (n_frames, n_vertices, 3) target rest pose (float32 for planar)
    markers: np.ndarray                  # (n_frames, n_used, 3) retargeted markers on the target
    labels: list                         # used marker labels
    rigid: list                          # labels of the rigid set used
    gaps: GapReport = field(default_factory=GapReport)
    triangulation: Triangulation | None = None
    rebuilt: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def lip_siblings(labels) -> dict:
    """``{inner index: outer index}`` by label: ``*Inner*`` pairs with the same label with ``Outer``."""
    pos = {s: i for i, s in enumerate(labels)}
    out = {}
    for i, s in enumerate(labels):
        for a, b in (("Inner", "Outer"), ("inner", "outer"), ("INNER", "OUTER")):
            if a in s and s.replace(a, b) in pos:
                out[i] = pos[s.replace(a, b)]
                break
    return out


def clean_take(positions, labels, rigid_names=None, max_gap: int = 12):
    """Steps 1-2: rigid removal then gap filling; returns (positions, rigid labels, GapReport, notes).

    ``notes``: one line per rigid marker rejected as an outlier in some frames (named set only).
    """
    x = np.asarray(positions, dtype=np.float64)
    labels = list(labels)
    dead = ~np.isfinite(x).all(axis=2).any(axis=0)
    rigid = None
    if rigid_names:
        pos = {s: i for i, s in enumerate(labels)}
        unknown = [s for s in rigid_names if s not in pos]
        if unknown:
            raise InputError(f"--rigid: unknown marker label(s) {unknown}; the take has {', '.join(labels)}")
        rigid = [pos[s] for s in rigid_names]
    live = np.flatnonzero(~dead)
    if rigid is None:
        rr = remove_rigid_motion(x[:, live], None, labels=[labels[i] for i in live])
        used = [labels[live[i]] for i in rr.rigid]
        stab = np.full_like(x, np.nan)
        stab[:, live] = rr.positions
    else:
        rr = remove_rigid_motion(x, rigid, labels=labels)
        used = [labels[i] for i in rr.rigid]
        stab = rr.positions
    filled = stab.copy()
    f, report = fill_gaps(stab[:, live], max_gap=max_gap, labels=[labels[i] for i in live])
    filled[:, live] = f
    report.unfillable += [(labels[i], 0, len(x)) for i in np.flatnonzero(dead)]
    notes = [f"rigid set: {lab} rejected as an outlier in {n} frame(s), first {first} "
             f"(more than {rr.threshold:.3g} from the others' rigid fit)" for lab, n, first in rr.rejected_report(labels)]
    return filled, used, report, notes


#: the longest gap (frames) filled without a report; the planar bones' radius over the shortest control edge
MAX_GAP, RADIUS_SCALE = 12, 1.5


def drive_mesh(positions, labels, target_vertices, target_markers: dict, method: str = "planar",
               rigid_names=None, regions=None, up=(0.0, 1.0, 0.0), forward=(0.0, 0.0, 1.0)) -> DriveResult:
    """Drive ``target_vertices`` with a marker take.

    Parameters
    ----------
    positions : (n_frames, n_markers, 3) source take (any units; the RBF absorbs the scale)
    labels : marker labels of the take
    target_vertices : (n_vertices, 3) target mesh at rest
    target_markers : dict label -> (3,) point on the target; only these labels are used
    method : "planar", "imq", "tps" or "gaussian"
    rigid_names : labels of a rigid set (head jig), optional
    regions : list of :class:`retarget.mocap.masks.Region`, optional (planar only)
    up, forward : the target mesh's axes

    Gaps up to :data:`MAX_GAP` frames are filled without a report; the planar bones' radius is
    :data:`RADIUS_SCALE` times the shortest connected control edge; the triangulation never joins the upper
    and the lower inner lips.
    """
    if method not in METHODS:
        raise InputError(f"--method: expected one of {', '.join(METHODS)}, got {method!r}")
    labels = list(labels)
    tv = np.asarray(target_vertices, dtype=np.float64)
    use = [s for s in labels if s in target_markers]
    missing_t = [s for s in target_markers if s not in labels]
    notes = []
    if missing_t:
        notes.append(f"target markers not in the take (ignored): {missing_t}")
    if len(use) < 4:
        raise InputError(f"only {len(use)} marker label(s) of the take are in the target markers; need 4 or more")
    x, rigid_used, gaps, clean_notes = clean_take(positions, labels, rigid_names, MAX_GAP)
    notes += clean_notes
    idx = np.array([labels.index(s) for s in use])
    src = x[:, idx]
    tgt = np.array([target_markers[s] for s in use], dtype=np.float64)
    # step 3: markers never seen -> place on source from the target (inverse map), rebuild from siblings
    dead = ~np.isfinite(src).all(axis=2).any(axis=0)
    rebuilt = []
    if dead.any():
        live = ~dead
        inv = RBF("imq", labels=[use[i] for i in np.flatnonzero(live)]).fit(tgt[live], src[0, live])
        ref = src[0].copy()
        ref[dead] = inv(tgt[dead])
        sib = {i: o for i, o in lip_siblings(use).items() if dead[i] and not dead[o]}
        if sib:
            src = rebuild_inner_lips(src, ref, sib)
            rebuilt = [use[i] for i in sib]
        still = ~np.isfinite(src).all(axis=2).all(axis=0)
        if still.any():
            # others from the rigid motion of their neighbours (section 5.2, e.g. the outer eye corner)
            src, rep2 = fill_gaps(src, reference=ref, max_gap=len(src), labels=use)
            rebuilt += [s for s, _, _ in rep2.filled + rep2.long]
    bad = ~np.isfinite(src).all(axis=2)
    if bad.any():
        f, m = np.argwhere(bad)[0]
        raise InputError(f"marker {use[m]!r} is still missing at frame {f} after gap filling "
                         f"({bad.sum()} marker-frames in all): too few visible neighbours")
    retarget = RBF("imq", labels=use).fit(src[0], tgt)                 # eqs. (14)-(16)
    mk = retarget(src)                                                          # (n_frames, n_used, 3)
    tri = None
    if method == "planar":
        up_in = {s for s in use if "Inner" in s and ("Up" in s or "Upper" in s)}
        lo_in = {s for s in use if "Inner" in s and ("Lo" in s or "Lower" in s)}
        forbid = [(up_in, lo_in)] if up_in and lo_in else []
        tri = triangulate_markers(mk[0], use, up, forward, forbid=forbid)
        masks = None
        if regions:
            from keyshape.retarget.mocap.masks import allowed_matrix

            masks = allowed_matrix(regions, tri.triangles, use, len(tv))
        # float32: what the command stores; within 5e-7 of the mesh's extent from the float64 map, ~1.5x faster
        bones = PlanarBones(radius_scale=RADIUS_SCALE, unbound="fade", labels=use,
                            dtype="float32").fit(tv, mk[0], tri.triangles, masks=masks)
        verts = bones.deform_many(mk)
    else:
        deformer = RBF(method, labels=use).fit(mk[0], mk)
        basis = deformer.basis(tv)
        verts = np.einsum("pk,fkc->fpc", basis, deformer.coef_)
        if not deformer.affine_:
            verts += tv
    return DriveResult(verts, mk, use, rigid_used, gaps, tri, rebuilt, notes)
