"""Write retargeted animation, chosen by the extension of the output path (.glb, .usda/.usdc/.usd, .csv,
.mp4/.avi or a folder of OBJ/PNG frames: docs/retarget.md, "Outputs")."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_dir
from keyshape.base.formats import Morphs
from keyshape.retarget.headpose import HeadMotion
from keyshape.retarget.targets.retargeter import Retargeter, clamp_weights
from keyshape.retarget.targets.target_set import name_key
from keyshape.base.formats.weights import write_weights
# the Live Link Face names and CSV layout live with the format (ARKIT52, LIVELINK_TAIL re-exported here)
from keyshape.base.formats.livelink import ARKIT52, LIVELINK_TAIL, csv_rows  # noqa: F401
from keyshape.base.formats.livelink import write_csv as write_livelink

VIDEO_SUFFIXES = (".mp4", ".avi")
USD_SUFFIXES = (".usda", ".usdc", ".usd")


def output_kind(path: str | Path, dim: int) -> str:
    """``"glb"``, ``"usd"``, ``"csv"``, ``"video"``, ``"obj_frames"`` or ``"png_frames"`` for ``path``."""
    suffix = Path(path).suffix.lower()
    kind = {".glb": "glb", ".csv": "csv", **dict.fromkeys(USD_SUFFIXES, "usd"),
            **dict.fromkeys(VIDEO_SUFFIXES, "video")}.get(suffix)
    if kind is None and (suffix == "" or Path(path).is_dir()):
        kind = "obj_frames" if dim == 3 else "png_frames"
    if kind is not None:
        return kind
    raise InputError("output must end in .glb, .usda/.usdc/.usd, .csv, .mp4/.avi, or be a folder (OBJ or PNG "
                     "frames)", path)


def livelink_values(names, weights: np.ndarray, head: HeadMotion | None = None,
                    eyes: np.ndarray | None = None) -> np.ndarray:
    """The 61 Live Link Face values of every frame, (n_frames, 61) in the CSV's column order.

    Target names are matched to ARKit names case-insensitively with ``_L``/``Left`` alike;
    an unsided ARKit name (``browInnerUp``, ``cheekPuff``) missing from the targets takes the
    mean of its ``_L``/``_R`` targets (ICT-FaceKit splits them). Unmatched ARKit columns are 0.
    ``HeadYaw``, ``HeadPitch``, ``HeadRoll``: the 3D head's angles in radians (``head.angles``; yaw > 0
    when the actor turns to their left, pitch > 0 when they look down, roll > 0 when the head tilts
    toward their right shoulder: the head axes of ARKit's face anchor, x the face's left, y up, z out
    of the face, ``R = Rz(roll) Ry(yaw) Rx(pitch)``); with a 2D head motion only ``HeadRoll`` (its
    in-plane angle) is set. The eye columns take ``eyes`` (n_frames, 4): left yaw, left pitch, right
    yaw, right pitch in radians (the actor's left and right eyes), when given.
    Raises :class:`InputError` when no target name is an ARKit name.
    One mapping for the CSV (:func:`~keyshape.base.formats.livelink.csv_rows` of these values) and the live
    packets (``keyshape live``).
    """
    weights = np.asarray(weights, dtype=np.float64)
    col = {name_key(n): j for j, n in enumerate(names)}
    out = np.zeros((len(weights), len(ARKIT52) + len(LIVELINK_TAIL)))
    hit = 0
    for a, n in enumerate(ARKIT52):
        k = name_key(n)
        if k in col:
            out[:, a] = weights[:, col[k]]
            hit += 1
        elif k + "left" in col and k + "right" in col:
            out[:, a] = (weights[:, col[k + "left"]] + weights[:, col[k + "right"]]) / 2
            hit += 1
    if not hit:
        raise InputError(f"no target name is an ARKit blendshape name (targets: {', '.join(list(names)[:8])}...); "
                         "the Live Link layout needs ARKit-named targets")
    tail = out[:, len(ARKIT52):]
    if head is not None and head.angles is not None:
        tail[:, 0:3] = head.angles
    elif head is not None:
        tail[:, 2] = head.angle
    if eyes is not None:
        tail[:, [3, 4, 6, 7]] = np.nan_to_num(np.asarray(eyes, np.float64))
    return out


def write_mesh_take(path: Path, mesh, base: np.ndarray, morphs: Morphs, meters_per_unit: float = 0.01,
                    sparse_targets: bool = False) -> dict:
    """The .glb or USD take (by ``path``'s extension) of a mesh (OBJ topology, UVs, materials) and its shapes
    (``morphs.deltas`` from ``base``): one writer for sculpted targets and rigs, with the vertex normals and
    each shape's normal offsets. ``meters_per_unit``: USD's ``metersPerUnit`` (:class:`ExportOptions`);
    ``sparse_targets``: the .glb's morph targets stored sparse. Returns what the USD writer reports ({} for .glb)."""
    from dataclasses import replace

    from keyshape.base.geometry import vertex_normals
    n0 = vertex_normals(base, mesh.triangles)
    nd = np.stack([vertex_normals(base + d, mesh.triangles) - n0 for d in morphs.deltas]) if len(morphs.deltas) \
        else None
    if output_kind(path, 3) == "glb":
        from keyshape.base.formats.gltf import split_at_uv_seams, write_glb
        from keyshape.retarget.rig.model import material_parts
        ids, uvs, tri = split_at_uv_seams(mesh)
        write_glb(path, base[ids], tri, replace(morphs, deltas=morphs.deltas[:, ids], normals=n0[ids],
                                                normal_deltas=None if nd is None else nd[:, ids]),
                  uvs=uvs, parts=material_parts(mesh), sparse_targets=sparse_targets)
        return {}
    from keyshape.base.formats.usd import write_usd
    keep = [i for i, p in enumerate(mesh.polygons) if len(p) >= 3]
    if not keep:
        raise InputError("the mesh has no faces: USD output needs faces")
    polys = [mesh.polygons[i] for i in keep]
    puv = [mesh.polygon_uvs[i] for i in keep] if len(mesh.uvs) and len(mesh.polygon_uvs) == len(mesh.polygons) \
        else None
    return write_usd(path, base, polys, replace(morphs, normals=n0, normal_deltas=nd),
                     uvs=mesh.uvs if puv is not None else None, polygon_uvs=puv, meters_per_unit=meters_per_unit)


#: the curves CSV's head columns (:func:`head_columns`)
HEAD_COLUMNS = ("headYaw", "headPitch", "headRoll", "headX", "headY", "headZ")


def head_columns(head: HeadMotion) -> np.ndarray:
    """(n_frames, 6) the curves CSV's ``headYaw, headPitch, headRoll`` (degrees, as Live Link's
    HeadYaw/Pitch/Roll) and ``headX, headY, headZ`` (the head node's translation, mesh units, y up, z
    toward the camera: depth) of a head motion; a 2D motion has yaw and pitch 0."""
    ang = head.angles if head.angles is not None else np.stack(
        [np.zeros(head.n_frames), np.zeros(head.n_frames), head.angle], 1)
    return np.concatenate([np.degrees(ang), head.translation], 1)


def _draw_2d(points: np.ndarray, size=(480, 480), scheme=None):
    """Frames of a drawn 2D character: (n_frames, h, w, 3) generator, one common framing."""
    import cv2
    w, h = size
    lo, hi = np.nanmin(points.reshape(-1, 2), axis=0), np.nanmax(points.reshape(-1, 2), axis=0)
    s = 0.9 * min(w / max(hi[0] - lo[0], 1e-9), h / max(hi[1] - lo[1], 1e-9))
    off = np.array([w, h]) / 2 - s * (lo + hi) / 2
    for p in points:
        img = np.full((h, w, 3), 255, np.uint8)
        q = p * s + off
        if scheme is not None:
            from keyshape.base.draw import draw_shape
            img = draw_shape(img, q, scheme, colour=(40, 40, 40), thickness=2)
        else:
            qi = np.round(q * 16).astype(np.int32)
            cv2.polylines(img, [qi.reshape(-1, 1, 2)], False, (40, 40, 40), 2, cv2.LINE_AA, 4)
        yield img


def _scheme_for(n_points: int, scheme):
    from keyshape.base.schemes import BUILTIN, load_scheme
    if scheme is not None:
        return load_scheme(scheme)
    return next((s for s in map(load_scheme, BUILTIN) if s.n_points == n_points), None)


def _head_2d(points: np.ndarray, head: HeadMotion) -> np.ndarray:
    """Apply head motion to 2D drawings (image axes, y down) about the drawing's first-frame centre."""
    c = points[0].mean(axis=0)
    ang = -head.angle                          # back to image axes
    cs, sn = np.cos(ang), np.sin(ang)
    rot = np.stack([np.stack([cs, -sn], -1), np.stack([sn, cs], -1)], -2) * head.scale[:, 0, None, None]
    t = head.translation[:, :2] * np.array([1.0, -1.0])
    return np.einsum("fij,fpj->fpi", rot, points - c) + c + t[:, None]


#: frames transformed at a time (bounds the memory, not the output) and the drawn frames' size (PNG, video)
CHUNK_FRAMES = 256
FRAME_SIZE = (480, 480)


@dataclass(frozen=True)
class ExportOptions:
    """How :func:`export` writes an animation (what ``Animation.export`` takes as keywords).

    Attributes
    ----------
    clamp : clamp weights to [0, 1] in .glb and .csv outputs (default keep: NNLS weights may exceed 1)
    livelink : .csv in the Live Link Face layout instead of ``frame,<target names>``
    bake_head : bake the head motion into OBJ/PNG/video frames (the .glb always carries it as node animation)
    scheme : landmark scheme for drawing 2D targets (default: a built-in one with the same point count)
    meters_per_unit : the meshes' length unit in metres (USD ``metersPerUnit``; default centimetres)
    """

    clamp: bool = False
    livelink: bool = False
    bake_head: bool = False
    scheme: object = None
    meters_per_unit: float = 0.01


def export(path: str | Path, rt: Retargeter, frames: np.ndarray, weights: np.ndarray, fps: float = 30.0,
           head: HeadMotion | None = None, options: ExportOptions | None = None) -> dict:
    """Write the retargeted animation to ``path`` (kind by extension: docs/retarget.md, "Outputs").

    Parameters
    ----------
    rt : fitted :class:`~retarget.targets.retargeter.Retargeter`
    frames : (n_frames,) frame numbers; weights : (n_frames, n_keys)
    fps : frame rate of the animation (glTF sampler times ``i / fps``, Live Link timecode)
    head : root motion (glTF node animation; baked into OBJ/PNG/video frames only with ``options.bake_head``)
    options : :class:`ExportOptions` (default: its defaults)

    Returns
    -------
    dict with ``kind``, ``path`` and ``n_clamped``. Nothing is left at ``path`` on error. A folder
    output follows the running command's ``--overwrite`` and inputs (:func:`~keyshape.base.files.atomic_dir`).
    """
    o = options if options is not None else ExportOptions()
    clamp, livelink, bake_head, scheme = o.clamp, o.livelink, o.bake_head, o.scheme
    chunk_frames, size = CHUNK_FRAMES, FRAME_SIZE
    rt._fitted()
    ts = rt.targets_
    kind = output_kind(path, ts.dim)
    path = Path(path)
    weights = np.asarray(weights, dtype=np.float64)
    if head is not None and head.n_frames != len(weights):
        raise InputError(f"head motion has {head.n_frames} frames but the weights have {len(weights)}")
    info = {"kind": kind, "path": path, "n_clamped": 0}
    if kind in ("glb", "usd"):
        if kind == "usd":
            from keyshape.base.formats.usd import require_usd
            require_usd()
            if ts.dim != 3:
                raise InputError("USD output needs 3D (OBJ) targets; these are 2D drawings")
        base, deltas, names, mw, info["n_clamped"] = rt.morph_targets(weights, clamp=clamp)
        if ts.mesh is None or not len(ts.mesh.triangles):
            raise InputError(f"the target meshes have no faces: {'.glb' if kind == 'glb' else 'USD output'} needs "
                             "faces", ts.files[0])
        info.update(write_mesh_take(path, ts.mesh, base, Morphs(deltas, names, mw, fps, head, np.asarray(frames)),
                                    o.meters_per_unit))
        if kind == "glb":
            info["n_morph_targets"] = len(names)
        return info
    if kind == "csv":
        w, info["n_clamped"] = clamp_weights(weights, clamp)
        names = list(ts.names)
        if livelink:
            write_livelink(path, livelink_values(names, w, head), fps)
        else:
            from keyshape.retarget.targets.retargeter import _unique
            write_weights(path, frames, _unique(names, ts.columns), w, fps=fps)
        return info
    out = rt.transform(weights, chunk_frames=chunk_frames)
    if kind == "obj_frames":
        from keyshape.base.formats.obj import write_obj
        if bake_head and head is not None:
            out = head.apply(out)
        with atomic_dir(path, kind="retarget") as tmp:
            for fr, v in zip(frames, out):
                write_obj(tmp / f"frame_{int(fr):06d}.obj", ts.mesh, v)
        return info
    import cv2
    if ts.dim == 2:
        pts = _head_2d(out, head) if (head is not None and bake_head) else out
        images = _draw_2d(pts, size, _scheme_for(ts.n_vertices, scheme))
    else:
        from keyshape.retarget.output.render import render_frames
        verts = head.apply(out) if (head is not None and bake_head) else out
        images = render_frames(verts, ts.mesh.triangles, size)
    if kind == "png_frames":
        with atomic_dir(path, kind="retarget") as tmp:
            for fr, img in zip(frames, images):
                cv2.imwrite(str(tmp / f"frame_{int(fr):06d}.png"), img)
    else:
        from keyshape.base.formats.video import video_writer
        with video_writer(path, fps, size) as wr:
            for img in images:
                wr.write(img)
    return info
