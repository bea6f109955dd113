"""glTF 2.0 binary (.glb) output: base mesh, morph targets, weight and head-motion animation.

Written with pygltflib. The layout (node ``head`` with child ``face``, one primitive per material, the
``performance`` animation) and why weights above 1 are kept: docs/retarget.md, "Outputs", and docs/formats.md.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_path
from keyshape.base.formats import Morphs

FLOAT, UINT = 5126, 5125
#: sparse morph targets: a vertex moving less than this fraction of the mesh's bounding-box diagonal
#: is stored as still (ICT-FaceKit: 0.5 um; float32 positions of the head resolve about 2 um); a
#: normal changing less than this (unit normals) likewise. The OBJ files' rounding leaves such
#: motions over a third of ICT-FaceKit's head in every shape.
SPARSE_POSITION_TOL = 1e-6
SPARSE_NORMAL_TOL = 1e-5


def _bounds(array: np.ndarray, minmax: bool) -> dict:
    """An accessor's ``min``/``max`` per component (glTF requires them on positions), or {}."""
    if not minmax:
        return {}
    a = np.asarray(array).reshape(len(array), -1)
    return dict(min=[float(x) for x in a.min(axis=0)], max=[float(x) for x in a.max(axis=0)])


class _Blob:
    """Accumulates tightly packed, 4-byte aligned buffer views and their accessors."""

    def __init__(self, gltf):
        self.gltf, self.parts, self.offset = gltf, [], 0

    def add(self, array: np.ndarray, type_: str, component: int, target: int | None = None,
            minmax: bool = False) -> int:
        import pygltflib as g
        view = self._view(np.ascontiguousarray(array).tobytes(), target)
        self.gltf.accessors.append(g.Accessor(bufferView=view, componentType=component,
                                              count=len(array), type=type_, **_bounds(array, minmax)))
        return len(self.gltf.accessors) - 1

    def _view(self, data: bytes, target: int | None = None) -> int:
        import pygltflib as g
        self.gltf.bufferViews.append(g.BufferView(buffer=0, byteOffset=self.offset, byteLength=len(data),
                                                  target=target))
        pad = (-len(data)) % 4
        self.parts.append(data + b"\0" * pad)
        self.offset += len(data) + pad
        return len(self.gltf.bufferViews) - 1

    def add_sparse(self, array: np.ndarray, minmax: bool = False, tol: float = 0.0) -> int:
        """A float VEC3 accessor stored sparse (glTF 2.0 ``accessor.sparse`` over implicit zeros): only the
        rows with a component beyond ``tol`` (the others read back as 0), with their indices; dense where
        that would not be smaller. A morph target that moves part of the face costs that part."""
        import pygltflib as g
        a = np.array(array, dtype=np.float32)
        keep = np.any(np.abs(a) > tol, axis=1)
        a[~keep] = 0.0
        rows = np.flatnonzero(keep)
        if 16 * len(rows) >= 12 * len(a):
            return self.add(a, "VEC3", FLOAT, g.ARRAY_BUFFER, minmax=minmax)
        sparse = None
        if len(rows):
            sparse = g.Sparse(count=len(rows),
                              indices=g.AccessorSparseIndices(bufferView=self._view(rows.astype(np.uint32).tobytes()),
                                                              componentType=UINT),
                              values=g.AccessorSparseValues(bufferView=self._view(a[rows].tobytes())))
        self.gltf.accessors.append(g.Accessor(componentType=FLOAT, count=len(a), type="VEC3", sparse=sparse,
                                              byteOffset=None, **_bounds(a, minmax)))
        return len(self.gltf.accessors) - 1

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def split_at_uv_seams(mesh) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """glTF vertices for an OBJ mesh: one per distinct (vertex, uv) corner pair.

    glTF stores one UV per vertex, OBJ one per polygon corner; a vertex on a UV seam
    becomes several glTF vertices at the same position (and with the same morph deltas).

    Returns
    -------
    vertex_ids : (n_gltf,) index into ``mesh.vertices`` of each glTF vertex
    uvs : (n_gltf, 2) float32 in glTF convention (``v`` flipped: origin top-left), or None
        when some polygon has no UVs (then ``vertex_ids`` is the identity)
    triangles : (n_triangles, 3) indices into the glTF vertices (polygons fan-triangulated)
    """
    polys = mesh.polygons
    have_uv = len(mesh.uvs) and polys and all(t is not None for t in mesh.polygon_uvs)
    if not have_uv:
        return np.arange(mesh.n_vertices), None, mesh.triangles
    sizes = np.array([len(p) for p in polys])
    v = np.concatenate(polys).astype(np.int64)
    t = np.concatenate(mesh.polygon_uvs).astype(np.int64)
    pairs, corner = np.unique(np.stack([v, t], axis=1), axis=0, return_inverse=True)
    corner = corner.reshape(-1)
    starts = np.cumsum(sizes) - sizes
    fan = [np.stack([np.full(k - 2, s), np.arange(s + 1, s + k - 1), np.arange(s + 2, s + k)], axis=1)
           for s, k in zip(starts, sizes) if k >= 3]
    tri = corner[np.concatenate(fan)] if fan else np.zeros((0, 3), np.int64)
    uv = mesh.uvs[pairs[:, 1]].astype(np.float32)
    uv[:, 1] = 1.0 - uv[:, 1]
    return pairs[:, 0], uv, tri


def write_glb(path: str | Path, base: np.ndarray, triangles: np.ndarray, morphs: Morphs, *,
              uvs: np.ndarray | None = None, parts: Sequence | None = None,
              default_weights: np.ndarray | None = None, sparse_targets: bool = False) -> None:
    """Write a .glb atomically.

    Parameters
    ----------
    base : (n_vertices, 3) base shape (the neutral, or the first target)
    triangles : (n_triangles, 3) vertex indices
    morphs : the morph targets (names in ``mesh.extras.targetNames``) and the take (weights None: no animation);
        the sampler times are ``frame / fps`` from the first frame on, the scene's ``extras`` hold ``fps``,
        ``frame_start`` and ``frame_end`` (Blender keeps them as custom properties; ``bench/blender_import_curves.py``
        sets the scene's frame range from them)
    uvs : (n_vertices, 2) ``TEXCOORD_0`` (see :func:`split_at_uv_seams`), or None
    parts : [(material name, triangle indices, (r, g, b, a)), ...]: one primitive per material
        sharing the vertex attributes and morph targets (default one ``skin`` primitive)
    default_weights : (n_targets,) ``mesh.weights`` (default zeros)
    sparse_targets : store each morph target sparse (glTF ``accessor.sparse``: only the vertices it
        moves, beyond :data:`SPARSE_POSITION_TOL` of the mesh's size), as for a rig whose shapes each
        move a part of the head

    See :func:`retarget.output.export.morph_targets` for how target shapes, regions and the
    absolute form become glTF deltas and weights exactly.
    """
    import pygltflib as g
    base, tg, weights, nd = morphs.checked(base)
    names, fps, head, normals = morphs.names, morphs.fps, morphs.head, morphs.normals
    first_frame = int(morphs.frames[0]) if morphs.frames is not None and len(morphs.frames) else 0
    tri = np.asarray(triangles)
    if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
        raise InputError(f"triangles: expected (n_triangles, 3) with at least one, got {tri.shape}")
    gltf = g.GLTF2(asset=g.Asset(version="2.0", generator="keyshape"))
    blob = _Blob(gltf)
    pos = blob.add(base.astype(np.float32), "VEC3", FLOAT, g.ARRAY_BUFFER, minmax=True)
    if parts is None:
        parts = [("skin", np.arange(len(tri)), (0.8, 0.72, 0.66, 1.0))]
    nd = None if nd is None else nd.astype(np.float32)
    tgt = []
    scale = float(np.linalg.norm(np.ptp(base, axis=0))) if len(base) else 0.0
    for i, d in enumerate(tg.astype(np.float32)):
        if sparse_targets:
            t = {"POSITION": blob.add_sparse(d, minmax=True, tol=SPARSE_POSITION_TOL * scale)}
            if nd is not None:
                t["NORMAL"] = blob.add_sparse(nd[i], tol=SPARSE_NORMAL_TOL)
        else:
            t = {"POSITION": blob.add(d, "VEC3", FLOAT, g.ARRAY_BUFFER, minmax=True)}
            if nd is not None:
                t["NORMAL"] = blob.add(nd[i], "VEC3", FLOAT, g.ARRAY_BUFFER)
        tgt.append(t)
    dw = np.zeros(len(tg)) if default_weights is None else np.asarray(default_weights, dtype=np.float64)
    attrs = g.Attributes(POSITION=pos)
    if normals is not None:
        attrs.NORMAL = blob.add(np.asarray(normals, np.float32), "VEC3", FLOAT, g.ARRAY_BUFFER)
    if uvs is not None:
        if np.shape(uvs) != (len(base), 2):
            raise InputError(f"uvs: expected ({len(base)}, 2), got {np.shape(uvs)}")
        attrs.TEXCOORD_0 = blob.add(np.asarray(uvs, np.float32), "VEC2", FLOAT, g.ARRAY_BUFFER)
    prims = []
    for name, sel, rgba in parts:
        if not len(sel):
            continue
        idx = blob.add(tri[np.asarray(sel)].astype(np.uint32).reshape(-1), "SCALAR", UINT,
                       g.ELEMENT_ARRAY_BUFFER, minmax=False)
        gltf.materials.append(g.Material(name=str(name), pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorFactor=[float(x) for x in rgba], metallicFactor=0.0, roughnessFactor=0.7),
            alphaMode="BLEND" if rgba[3] < 1 else "OPAQUE"))
        prims.append(g.Primitive(attributes=attrs, indices=idx, targets=tgt, mode=4,
                                 material=len(gltf.materials) - 1))
    gltf.meshes.append(g.Mesh(name="face", primitives=prims, weights=[float(x) for x in dw],
                              extras={"targetNames": [str(n) for n in names]}))
    gltf.nodes.append(g.Node(name="head", children=[1]))
    gltf.nodes.append(g.Node(name="face", mesh=0))
    n_frames = 0 if weights is None else len(weights)
    extras = {"fps": float(fps)}
    if n_frames:
        extras.update(frame_start=int(first_frame), frame_end=int(first_frame + n_frames - 1))
    gltf.scenes.append(g.Scene(name="scene", nodes=[0], extras=extras))
    gltf.scene = 0
    if weights is not None and len(weights):
        times = ((first_frame + np.arange(len(weights))) / fps).astype(np.float32)
        t_acc = blob.add(times, "SCALAR", FLOAT, minmax=True)
        samplers = [g.AnimationSampler(input=t_acc, output=blob.add(weights.astype(np.float32).reshape(-1),
                                                                    "SCALAR", FLOAT), interpolation="LINEAR")]
        channels = [g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=1, path="weights"))]
        if head is not None:
            for what, arr, typ in (("translation", head.translation, "VEC3"), ("rotation", head.rotation, "VEC4"),
                                   ("scale", head.scale, "VEC3")):
                samplers.append(g.AnimationSampler(input=t_acc, output=blob.add(arr.astype(np.float32), typ, FLOAT),
                                                   interpolation="LINEAR"))
                channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                                   target=g.AnimationChannelTarget(node=0, path=what)))
        gltf.animations.append(g.Animation(name="performance", samplers=samplers, channels=channels))
    data = blob.bytes()
    gltf.buffers.append(g.Buffer(byteLength=len(data)))
    gltf.set_binary_blob(data)
    with atomic_path(path) as tmp:
        gltf.save_binary(str(tmp))
