"""``keyshape mocap``: a marker take (C3D/TRC/CSV) drives a dense target mesh (001 sections 4-5)."""
from __future__ import annotations

import sys
from pathlib import Path


#: the .glb's principal-component morph targets (at most)
GLB_COMPONENTS = 32


def register(subparsers) -> None:
    """Add ``keyshape mocap``."""
    p = subparsers.add_parser(
        "mocap", help="drive a target mesh with 3D facial markers (RBF retargeting + planar bones)",
        description="Remove head motion, fill gaps, retarget the markers onto the target with an "
                    "IMQ RBF (first frame = relaxed face) and deform the target per frame with planar "
                    "bones (or an RBF deformer). Output: .npz (vertices per frame), a folder of OBJs, "
                    "or .glb (principal-component morph targets).")
    p.add_argument("markers", help="marker take: .c3d, .trc or .csv")
    p.add_argument("--target", required=True, help="target mesh .obj at rest")
    p.add_argument("--target-markers", required=True,
                   help="JSON: marker label -> vertex index of the target, or [x, y, z] on it")
    p.add_argument("--rigid", default=None,
                   help="comma-separated labels of a rigid set (head jig), or @file with them; "
                        "default: the most rigid markers, estimated")
    p.add_argument("--masks", default=None, help="discontinuity masks JSON (see docs/mocap.md)")
    p.add_argument("--method", default="planar", choices=["planar", "imq", "tps", "gaussian"])
    p.add_argument("--duplicate-labels", default="error", choices=["error", "rename"],
                   help="a take with two markers of one label: stop (default) or rename the second X to X#2")
    p.add_argument("--up", default="y", choices=["x", "y", "z"], help="the target mesh's up axis")
    p.add_argument("-o", "--output", required=True, help="OUT.npz, OUT.glb, or a folder for one OBJ per frame")
    p.add_argument("--overwrite", action="store_true",
                   help="write OBJ frames into a non-empty folder keyshape did not make (only its own "
                        "frame_NNNNNN.obj files are written; nothing is deleted)")
    p.set_defaults(func=_mocap)


def parse_rigid(spec: str) -> list[str]:
    """Labels of ``--rigid``: comma-separated, or ``@file`` with them (commas or lines); duplicates refused."""
    from keyshape.base.errors import InputError, require_file

    if spec.startswith("@"):
        path = require_file(spec[1:], "rigid-set file")
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            raise InputError("not a text file of marker labels", path) from None
        where = path
    else:
        text, where = spec, None
    names = [s.strip() for s in text.replace("\n", ",").split(",") if s.strip()]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"--rigid names {', '.join(dup)} more than once: a rigid set needs 3 distinct markers",
                         where)
    if len(names) < 3:
        raise InputError(f"--rigid gives {len(names)} marker(s): a rigid set needs at least 3", where)
    return names


def read_target_markers(path, n_vertices: int, vertices=None) -> dict:
    """Label -> (3,) point: a vertex index (checked against ``n_vertices``), an [x, y, z] point, or
    ``{"position": [x, y, z], "vertex": i}`` as ``keyshape register --out-markers`` writes
    (parsed by :func:`keyshape.base.formats.markers.read_mesh_markers`)."""
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.markers import read_mesh_markers

    out, bad = {}, []
    for lab, val in read_mesh_markers(path, "target markers file").items():
        if isinstance(val, int):
            if not 0 <= val < n_vertices:
                bad.append(f"{lab}: vertex {val}")
                continue
            out[lab] = None if vertices is None else np.asarray(vertices[val], dtype=np.float64)
        else:
            out[lab] = np.asarray(val, dtype=np.float64)
    if bad:
        raise InputError(f"unknown vertex index(es) (the mesh has {n_vertices} vertices): {', '.join(bad)}", path)
    if vertices is not None and out:
        check_target_markers(out, np.asarray(vertices, dtype=np.float64), path)
    return out


def check_target_markers(markers: dict, vertices, path) -> None:
    """Refuse target markers far from the mesh (farther than its bounding-box diagonal from the box:
    wrong units or a typo) and more than two markers on one point (a collapsed set)."""
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.markers import coincident_pairs

    lo, hi = vertices.min(0), vertices.max(0)
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    for lab, p in markers.items():
        if p is None:
            continue
        if not np.all(np.isfinite(p)):
            raise InputError(f"marker {lab!r}: position {p.tolist()} is not finite", path)
        out_by = float(np.linalg.norm(np.maximum(lo - p, 0) + np.maximum(p - hi, 0)))
        if out_by > diag:
            raise InputError(f"marker {lab!r} at {p.tolist()} is {out_by:.3g} units outside the target mesh "
                             f"(its size is {diag:.3g}): wrong units or a typo?", path)
    labels = [k for k, v in markers.items() if v is not None]
    pts = np.array([markers[k] for k in labels]).reshape(-1, 3)
    pairs = coincident_pairs(pts, 1e-9 * diag)
    names = sorted({labels[i] for ab in pairs for i in ab})
    if len(names) > 2:
        raise InputError(f"{len(names)} target markers on one point ({', '.join(names[:6])}"
                         f"{', ...' if len(names) > 6 else ''}): a collapsed marker set", path)


def _mocap(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_dir, atomic_path, check_output, check_output_dir
    from keyshape.retarget.mocap.drive import drive_mesh
    from keyshape.base.formats.markers import read_markers
    from keyshape.base.formats.obj import read_obj, write_obj

    rigid = parse_rigid(args.rigid) if args.rigid else None
    inputs = [args.markers, args.target, args.target_markers, args.masks,
              args.rigid[1:] if args.rigid and args.rigid.startswith("@") else None]
    out = Path(args.output)
    if out.suffix.lower() in (".npz", ".glb"):
        check_output(out, "file", inputs)
    else:
        check_output_dir(out, args.overwrite, inputs)
    take = read_markers(args.markers, duplicates=args.duplicate_labels)
    for w in take.warnings:
        print(f"keyshape mocap: warning: {w}", file=sys.stderr)
    mesh = read_obj(args.target, require_faces=True)
    tm = read_target_markers(args.target_markers, mesh.n_vertices, mesh.vertices)
    axes = {"x": ((1, 0, 0), (0, 0, 1)), "y": ((0, 1, 0), (0, 0, 1)), "z": ((0, 0, 1), (0, -1, 0))}
    up, fw = axes[args.up]
    regions = None
    used = [s for s in take.labels if s in tm]
    if args.masks:
        from keyshape.base.formats.masks import read_masks
        from keyshape.retarget.mocap.masks import regions_from_masks

        if args.method != "planar":
            raise InputError("--masks applies to --method planar only")
        regions = regions_from_masks(read_masks(args.masks), used, vertices=mesh.vertices,
                                     markers=np.array([tm[s] for s in used]), mesh=mesh, up=up, forward=fw)
    res = drive_mesh(take.positions, take.labels, mesh.vertices, tm, method=args.method, rigid_names=rigid,
                     regions=regions, up=up, forward=fw)
    print(f"{take.n_frames} frames at {take.rate:g} Hz, {take.n_markers} markers ({take.units}); "
          f"{len(res.labels)} drive the target; rigid set: {', '.join(res.rigid)}")
    print(res.gaps)
    if res.rebuilt:
        print(f"rebuilt from neighbours (never seen): {', '.join(res.rebuilt)}")
    if res.triangulation is not None:
        print(res.triangulation.report())
    for n in res.notes:
        print(n)
    verts = res.vertices
    if out.suffix.lower() == ".npz":
        with atomic_path(out) as tmp:
            np.savez(tmp, vertices=verts.astype(np.float32), markers=res.markers, labels=np.array(res.labels),
                     rate=take.rate, triangles=mesh.triangles)
    elif out.suffix.lower() == ".glb":
        from keyshape.base.formats.gltf import write_glb

        base = verts[0]
        d = (verts - base).reshape(len(verts), -1)
        u, s, vt = np.linalg.svd(d, full_matrices=False)
        k = min(GLB_COMPONENTS, len(s))
        energy = float((s[:k] ** 2).sum() / max((s ** 2).sum(), 1e-300))
        write_glb(out, base, mesh.triangles, vt[:k].reshape(k, -1, 3) * s[:k, None, None],
                  [f"pc{i:02d}" for i in range(k)], weights=u[:, :k], fps=take.rate)
        print(f"{k} principal morph targets keep {100 * energy:.3f}% of the motion energy")
    else:
        with atomic_dir(out, args.overwrite, inputs, kind="mocap") as tmp:
            for f in range(len(verts)):
                write_obj(tmp / f"frame_{f:06d}.obj", mesh, verts[f])
    print(f"wrote {out}")
    return 0
