"""Write a rig's own curves (from a pose library) by the output's extension.

=================  ==========================================================
``OUT.csv``        ``frame,time,<rig shape names>`` (what DCC import scripts read), or the
                   Live Link Face layout with ``livelink=True``
``OUT.glb``        the rig's neutral with every rig shape that moves in the take (a curve
                   not 0 throughout) as a morph target, their curves as the weight
                   animation (and the head motion)
``OUT.usda/.usdc``  USD (also ``.usd``): the rig's neutral with the shapes that move as UsdSkel
                   blend shapes (the rig's names), the curves per time code, the head joint
``OUT.mp4/.avi``   the shaded rig
``OUT`` (folder)   one OBJ per frame
=================  ==========================================================
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_dir, atomic_write, run_overwrite_inputs
from keyshape.retarget.headpose import HeadMotion
from keyshape.retarget.rig.model import Rig

#: frames evaluated (OBJ frames) or rendered (video) at a time: bounds the memory, not the output
CHUNK_FRAMES = 64


def export_rig(path: str | Path, rig: Rig, frames: np.ndarray, curves: np.ndarray, fps: float = 30.0,
               head: HeadMotion | None = None, livelink: bool = False,
               size=(480, 480), meters_per_unit: float = 0.01, eyes: np.ndarray | None = None) -> dict:
    """Write rig curves (n_frames, n_shapes) to ``path``; returns ``{"kind", "path"}``. Nothing is left on error.

    ``meters_per_unit``: the rig's length unit in metres (USD ``metersPerUnit``; ICT-FaceKit: cm, 0.01).
    With ``head`` the curves CSV gets the columns of :func:`~keyshape.retarget.output.export.head_columns`
    (``headYaw, headPitch, headRoll`` in degrees, ``headX, headY, headZ``), the Live Link CSV its
    HeadYaw/HeadPitch/HeadRoll and the .glb the head node's rotation and translation; ``eyes``
    (n_frames, 4: left yaw, left pitch, right yaw, right pitch, radians) go to the Live Link eye columns.
    A folder output follows the running command's ``--overwrite`` and inputs
    (:func:`~keyshape.base.files.run_overwrite_inputs`).
    """
    from keyshape.retarget.output.export import HEAD_COLUMNS, head_columns, livelink_rows, output_kind
    path = Path(path)
    curves = np.asarray(curves, dtype=np.float64)
    if curves.shape != (len(frames), rig.n_shapes):
        raise InputError(f"curves: expected ({len(frames)}, {rig.n_shapes}), got {curves.shape}")
    if head is not None and head.n_frames != len(curves):
        raise InputError(f"head motion has {head.n_frames} frames but the curves have {len(curves)}")
    kind = output_kind(path, 3)
    info = {"kind": kind, "path": path}
    if kind == "csv":
        if livelink:
            header, rows = livelink_rows(list(rig.names), curves, fps, head, eyes)
            with atomic_write(path, newline="") as f:
                wr = csv.writer(f)
                wr.writerow(header)
                wr.writerows(rows)
        else:
            from keyshape.base.formats.weights import write_weights
            if head is not None:
                write_weights(path, frames, list(rig.names) + list(HEAD_COLUMNS),
                              np.concatenate([curves, head_columns(head)], 1), fps=fps)
            else:
                write_weights(path, frames, list(rig.names), curves, fps=fps)
        return info
    if rig.mesh is None or not rig.mesh.polygons:
        raise InputError("the rig's neutral has no faces: .glb, video and OBJ output need faces", rig.neutral_file)
    if kind == "glb":
        from keyshape.base.formats.gltf import split_at_uv_seams, write_glb
        from keyshape.base.geometry import vertex_normals
        from keyshape.retarget.rig.model import material_parts
        ids, uvs, tri = split_at_uv_seams(rig.mesh)
        mt = rig.mesh.triangles
        # only the shapes that move, each stored sparse (the vertices it moves): a shape at 0 throughout
        # adds nothing but megabytes (26 of ICT-FaceKit's 53 shapes move on franck)
        moving = np.flatnonzero(np.abs(curves).max(axis=0) > 0) if len(curves) else np.zeros(0, np.intp)
        n0 = vertex_normals(rig.neutral, mt)
        nd = np.stack([vertex_normals(rig.neutral + rig.deltas[j], mt) - n0 for j in moving]) if len(moving) \
            else np.zeros((0, rig.n_vertices, 3))
        write_glb(path, rig.neutral[ids], tri, rig.deltas[moving][:, ids], [rig.names[j] for j in moving],
                  curves[:, moving], fps, head, uvs=uvs,
                  normals=n0[ids], normal_deltas=nd[:, ids], parts=material_parts(rig.mesh),
                  first_frame=int(frames[0]) if len(frames) else 0, sparse_targets=True)
        return info
    if kind == "usd":
        from keyshape.retarget.output.export import write_usd_take
        moving = np.flatnonzero(np.abs(curves).max(axis=0) > 0) if len(curves) else np.arange(0)
        info.update(write_usd_take(path, rig.mesh, rig.neutral, rig.deltas[moving], [rig.names[j] for j in moving],
                                   curves[:, moving], np.asarray(frames), fps, head, meters_per_unit))
        return info
    if kind == "obj_frames":
        from keyshape.base.formats.obj import write_obj
        with atomic_dir(path, *run_overwrite_inputs(), kind="retarget") as tmp:
            for s in range(0, len(curves), CHUNK_FRAMES):
                for fr, v in zip(frames[s:s + CHUNK_FRAMES], rig.evaluate(curves[s:s + CHUNK_FRAMES])):
                    write_obj(tmp / f"frame_{int(fr):06d}.obj", rig.mesh, v)
        return info
    if kind == "video":
        from keyshape.base.formats.video import video_writer
        from keyshape.retarget.output.preview import RigRenderer
        r = RigRenderer(rig, size=size).fit(curves)
        with video_writer(path, fps, size) as wr:
            for s in range(0, len(curves), CHUNK_FRAMES):
                for img in r.render_many(curves[s:s + CHUNK_FRAMES]):
                    wr.write(img)
        return info
    raise InputError(f"rig output {kind} not supported", path)
