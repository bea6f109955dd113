"""USD (``.usda``/``.usdc``/``.usd``) output: the mesh with UsdSkel blend shapes, a head joint and the take.

Written with Pixar's ``usd-core`` (``pip install keyshape[usd]``), never by hand; :func:`read_usd` reads a file back
and evaluates it with UsdSkel's own machinery. The stage's layout, time codes, units and precision:
docs/retarget.md, "USD".
"""
from __future__ import annotations

import contextlib
import os
import re

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_path
from keyshape.base.formats import Morphs

SUFFIXES = (".usda", ".usdc", ".usd")
JOINT = "head"


def require_usd():
    """The ``pxr`` modules, or a one-line :class:`InputError` naming the extra."""
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt
    except ImportError:
        raise InputError("USD output needs usd-core: pip install 'keyshape[usd]'") from None
    return Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt


def _prim_names(names: Sequence[str], tf) -> list[str]:
    """Valid, unique USD prim names for ``names`` (``Tf.MakeValidIdentifier``, ``_2`` on repeats)."""
    out, seen = [], set()
    for n in names:
        base = tf.MakeValidIdentifier(str(n)) or "shape"
        p, k = base, 2
        while p in seen:
            p, k = f"{base}_{k}", k + 1
        seen.add(p)
        out.append(p)
    return out


@contextlib.contextmanager
def _stderr_captured():
    """Send file descriptor 2 to a temporary file while the block runs; yields a function that returns
    what was written there (so that a failing USD save is one line, not thousands)."""
    import sys
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as buf:
        os.dup2(buf.fileno(), 2)
        text: list[str] = []
        try:
            yield lambda: "".join(text)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            buf.seek(0)
            text.append(buf.read(1 << 16).decode("utf-8", "replace"))


def _save_error(path: Path, said: str) -> OSError:
    """One line for a USD save that failed: disk full when the folder's disk has no room left, else what
    USD said first (the hidden temporary's name replaced by the user's path)."""
    import errno
    import shutil

    try:
        full = shutil.disk_usage(path.parent).free < (1 << 20)
    except OSError:
        full = False
    if full:
        return OSError(errno.ENOSPC, "no space left on the device", str(path))
    first = next((ln.strip() for ln in said.splitlines() if ln.strip()), "")
    first = re.sub(r"\S*\.partial\S*", path.name, first)[:200]
    return OSError(errno.EIO, f"USD could not write the file{': ' + first if first else ''}", str(path))


def write_usd(path: str | Path, points: np.ndarray, polygons: Sequence[np.ndarray], morphs: Morphs, *,
              uvs: np.ndarray | None = None, polygon_uvs: Sequence[np.ndarray] | None = None,
              meters_per_unit: float = 0.01) -> dict:
    """Write a mesh, its blend shapes and a take as one USD stage, atomically (layout: module docstring).

    Parameters
    ----------
    path : ``.usda`` (text), ``.usdc`` (binary crate) or ``.usd`` (crate)
    points : (n_vertices, 3) the base shape (the neutral)
    polygons : vertex indices of each face (as read from the OBJ)
    morphs : the blend shapes from ``points`` and the take (weights required; ``frames``: the time codes,
        strictly increasing; ``fps``: ``timeCodesPerSecond``; ``head``: the head joint's motion, None: at rest);
        the names made valid identifiers (``Tf.MakeValidIdentifier``) and unique; a rig's already are
    uvs, polygon_uvs : OBJ texture coordinates and, per face, the UV index of each corner
        (``primvars:st``, face-varying, indexed); None when some face has no UVs
    meters_per_unit : length of one mesh unit in metres (``metersPerUnit``)

    Returns
    -------
    dict: ``names`` (as written), ``n_shapes``, ``start``, ``end`` (time codes), ``n_offsets`` (sparse offsets written)

    Raises
    ------
    InputError
        usd-core missing, a wrong suffix or shape, non-finite weights, frames not increasing.
    """
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = require_usd()
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise InputError(f"USD output must end in {', '.join(SUFFIXES)}", path)
    names, fps, head, frames, normals = morphs.names, morphs.fps, morphs.head, morphs.frames, morphs.normals
    pts, d, w, nd = morphs.checked(points)
    if w is None:
        raise InputError("weights: a USD take needs them (n_frames, n_shapes)")
    if not (np.isfinite(meters_per_unit) and meters_per_unit > 0):
        raise InputError(f"metres per unit must be > 0, got {meters_per_unit}")
    if not polygons:
        raise InputError("the mesh has no faces: USD output needs faces")
    n = len(w)
    fr = np.arange(n) if frames is None else np.asarray(frames, dtype=np.int64)
    if fr.shape != (n,) or (n > 1 and np.any(np.diff(fr) <= 0)):
        raise InputError(f"frames: expected {n} strictly increasing frame numbers")
    start, end = (int(fr[0]), int(fr[-1])) if n else (0, 0)

    with atomic_path(path) as tmp:
        layer = Sdf.Layer.CreateNew(str(tmp), args={"format": "usda" if path.suffix.lower() == ".usda" else "usdc"})
        stage = Usd.Stage.Open(layer)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
        stage.SetTimeCodesPerSecond(float(fps))
        stage.SetFramesPerSecond(float(fps))
        stage.SetStartTimeCode(start)
        stage.SetEndTimeCode(end)
        root = UsdSkel.Root.Define(stage, "/Character")
        stage.SetDefaultPrim(root.GetPrim())
        skel = UsdSkel.Skeleton.Define(stage, "/Character/Skeleton")
        ident = Vt.Matrix4dArray([Gf.Matrix4d(1.0)])
        skel.CreateJointsAttr(Vt.TokenArray([JOINT]))
        skel.CreateBindTransformsAttr(ident)
        skel.CreateRestTransformsAttr(ident)
        anim = UsdSkel.Animation.Define(stage, "/Character/Skeleton/Performance")
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        anim.CreateJointsAttr(Vt.TokenArray([JOINT]))
        tokens = _prim_names(names, Tf)
        anim.CreateBlendShapesAttr(Vt.TokenArray(tokens))
        wa = anim.CreateBlendShapeWeightsAttr()
        ta, ra, sa = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
        if head is None:
            ta.Set(Vt.Vec3fArray([Gf.Vec3f(0.0)]))
            ra.Set(Vt.QuatfArray([Gf.Quatf(1.0)]))
            sa.Set(Vt.Vec3hArray([Gf.Vec3h(1.0)]))
        w32 = w.astype(np.float32)
        for i in range(n):
            t = Usd.TimeCode(float(fr[i]))
            wa.Set(Vt.FloatArray.FromNumpy(w32[i]), t)
            if head is not None:
                x, y, z, qw = (float(c) for c in head.rotation[i])
                ta.Set(Vt.Vec3fArray([Gf.Vec3f(*(float(c) for c in head.translation[i]))]), t)
                ra.Set(Vt.QuatfArray([Gf.Quatf(qw, x, y, z)]), t)
                sa.Set(Vt.Vec3hArray([Gf.Vec3h(*(float(c) for c in head.scale[i]))]), t)

        mesh = UsdGeom.Mesh.Define(stage, "/Character/Face")
        counts = np.array([len(p) for p in polygons], dtype=np.int32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.concatenate(polygons).astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, pts.min(axis=0))),
                                             Gf.Vec3f(*map(float, pts.max(axis=0)))]))
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(0.8, 0.72, 0.66)]))
        if uvs is not None and polygon_uvs is not None and len(polygon_uvs) == len(polygons) \
                and all(t is not None for t in polygon_uvs):
            st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                         UsdGeom.Tokens.faceVarying)
            st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uvs, dtype=np.float32)))
            st.SetIndices(Vt.IntArray.FromNumpy(np.concatenate(polygon_uvs).astype(np.int32)))
        if normals is not None:
            mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(normals, dtype=np.float32)))
            mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)

        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
        binding.CreateBlendShapesAttr(Vt.TokenArray(tokens))
        targets = []
        n_offsets = 0
        for j, pname in enumerate(tokens):
            moved = np.abs(d[j]).max(axis=1) > 0
            if nd is not None:
                moved |= np.abs(nd[j]).max(axis=1) > 0
            idx = np.flatnonzero(moved)
            if not len(idx):                                      # a shape that moves nothing: one zero offset
                idx = np.array([0])
            bs = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(pname))
            bs.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(d[j, idx].astype(np.float32)))
            bs.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(idx.astype(np.int32)))
            if nd is not None:
                bs.CreateNormalOffsetsAttr(Vt.Vec3fArray.FromNumpy(nd[j, idx].astype(np.float32)))
            targets.append(bs.GetPath())
            n_offsets += len(idx)
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
        with _stderr_captured() as said:                  # USD prints its C++ errors line by line
            try:
                saved = bool(stage.GetRootLayer().Save())
            except Tf.ErrorException:
                saved = False
        if not saved:
            raise _save_error(path, said())
        del stage, layer
    return {"names": tokens, "n_shapes": len(names), "start": start, "end": end, "n_offsets": n_offsets}


@dataclass
class UsdTake:
    """A USD take read back and evaluated by UsdSkel (see :func:`read_usd`).

    Attributes
    ----------
    names : blend shape names of the mesh (``skel:blendShapes``)
    times : (n,) the evaluated time codes
    weights : (n, n_shapes) blend shape weights (mesh order) at ``times``
    shaped : (n, n_vertices, 3) points after the blend shapes (skeleton space, no head motion)
    skinned : (n, n_vertices, 3) points after the blend shapes and the head joint's skinning
    normals : (n, n_vertices, 3) or None, normals after the blend shapes' normal offsets
    fps, frames_per_second : ``timeCodesPerSecond``, ``framesPerSecond``
    start, end : ``startTimeCode``, ``endTimeCode``
    meters_per_unit : ``metersPerUnit``; up_axis : ``upAxis``
    """

    names: list
    times: np.ndarray
    weights: np.ndarray
    shaped: np.ndarray
    skinned: np.ndarray
    normals: np.ndarray | None
    fps: float
    frames_per_second: float
    start: float
    end: float
    meters_per_unit: float
    up_axis: str


def read_usd(path: str | Path, times: Sequence[float] | None = None) -> UsdTake:
    """Read a stage written by :func:`write_usd` and evaluate its skinned mesh at ``times``.

    The evaluation is UsdSkel's: :class:`pxr.UsdSkel.Cache` finds the skeleton and the skinned
    mesh, the animation query gives the weights and joint transforms at each time, the
    blend-shape query (``ComputeSubShapeWeights``, ``ComputeDeformedPoints``) deforms the points
    (the normals: the schema's sum of ``normalOffsets``, the Python binding has no
    ``ComputeDeformedNormals``) and the skinning query
    (``ComputeSkinnedPoints``) applies the joint. ``times`` default to every time code from the
    start to the end.
    """
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = require_usd()
    from keyshape.base.errors import require_file
    stage = Usd.Stage.Open(str(require_file(path, "USD file")))
    if stage is None:
        raise InputError("not a USD stage", path)
    root = stage.GetDefaultPrim()
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(root), Usd.PrimDefaultPredicate)
    bindings = cache.ComputeSkelBindings(UsdSkel.Root(root), Usd.PrimDefaultPredicate)
    if not bindings or not bindings[0].GetSkinningTargets():
        raise InputError("no skinned mesh under the default prim", path)
    skel_query = cache.GetSkelQuery(bindings[0].GetSkeleton())
    sk_query = bindings[0].GetSkinningTargets()[0]
    mesh = UsdGeom.Mesh(sk_query.GetPrim())
    bs_query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(mesh.GetPrim()))
    point_indices = bs_query.ComputeBlendShapePointIndices()
    sub_offsets = bs_query.ComputeSubShapePointOffsets()
    has_normals = mesh.GetNormalsAttr().HasAuthoredValue()
    if has_normals:                   # the Python binding has no ComputeDeformedNormals: the schema's sum
        n_off = []
        for j in range(bs_query.GetNumBlendShapes()):
            bs = bs_query.GetBlendShape(j)
            idx = np.array(bs.GetPointIndicesAttr().Get(), dtype=np.int64)
            off = np.array(bs.GetNormalOffsetsAttr().Get(), dtype=np.float64).reshape(-1, 3)
            n_off.append((idx, off))
    anim_query = skel_query.GetAnimQuery()
    mapper = sk_query.GetBlendShapeMapper()
    names = [str(x) for x in sk_query.GetBlendShapeOrder()]
    if times is None:
        times = np.arange(stage.GetStartTimeCode(), stage.GetEndTimeCode() + 1)
    ws, shaped, skinned, normals = [], [], [], []
    for t in times:
        tc = Usd.TimeCode(float(t))
        w = mapper.Remap(anim_query.ComputeBlendShapeWeights(tc))
        ws.append(np.array(w, dtype=np.float64))
        sub_w, bs_idx, sub_idx = bs_query.ComputeSubShapeWeights(w)
        p = mesh.GetPointsAttr().Get(tc)
        if not bs_query.ComputeDeformedPoints(sub_w, bs_idx, sub_idx, point_indices, sub_offsets, p):
            raise InputError(f"UsdSkel could not apply the blend shapes at time {t}", path)
        shaped.append(np.array(p, dtype=np.float64))
        if has_normals:
            nrm = np.array(mesh.GetNormalsAttr().Get(tc), dtype=np.float64)
            for j, (idx, off) in enumerate(n_off):
                if len(off):
                    nrm[idx] += ws[-1][j] * off
            normals.append(nrm)
        xf = skel_query.ComputeSkinningTransforms(tc)
        if not sk_query.ComputeSkinnedPoints(xf, p, tc):
            raise InputError(f"UsdSkel could not skin the mesh at time {t}", path)
        skinned.append(np.array(p, dtype=np.float64))
    nv = len(mesh.GetPointsAttr().Get())
    return UsdTake(names, np.asarray(times, dtype=np.float64), np.array(ws).reshape(len(ws), len(names)),
                   np.array(shaped).reshape(-1, nv, 3), np.array(skinned).reshape(-1, nv, 3),
                   np.array(normals) if has_normals else None, stage.GetTimeCodesPerSecond(),
                   stage.GetFramesPerSecond(), stage.GetStartTimeCode(), stage.GetEndTimeCode(),
                   UsdGeom.GetStageMetersPerUnit(stage), str(UsdGeom.GetStageUpAxis(stage)))
