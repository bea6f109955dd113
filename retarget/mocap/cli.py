"""``keyshape mocap``: a marker take (C3D/TRC/CSV) drives a dense target mesh (001 sections 4-5)."""
from __future__ import annotations

from pathlib import Path


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
    p.add_argument("--max-gap", type=int, default=12, help="longest gap (frames) filled without a report")
    p.add_argument("--radius", type=float, default=1.5,
                   help="planar-bone radius as a multiple of the shortest connected control edge")
    p.add_argument("--components", type=int, default=32, help=".glb: number of morph targets")
    p.add_argument("--up", default="y", choices=["x", "y", "z"], help="the target mesh's up axis")
    p.add_argument("-o", "--output", required=True, help="OUT.npz, OUT.glb, or a folder for one OBJ per frame")
    p.set_defaults(func=_mocap)


def read_target_markers(path, n_vertices: int, vertices=None) -> dict:
    """Label -> (3,) point: a vertex index (checked against ``n_vertices``), an [x, y, z] point, or
    ``{"position": [x, y, z], "vertex": i}`` as ``keyshape register --out-markers`` writes
    (parsed by :func:`retarget.dense.io.read_markers`)."""
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.retarget.dense.io import read_markers

    out, bad = {}, []
    for lab, val in read_markers(path, "target markers file").items():
        if isinstance(val, int):
            if not 0 <= val < n_vertices:
                bad.append(f"{lab}: vertex {val}")
                continue
            out[lab] = None if vertices is None else np.asarray(vertices[val], dtype=np.float64)
        else:
            out[lab] = np.asarray(val, dtype=np.float64)
    if bad:
        raise InputError(f"unknown vertex index(es) (the mesh has {n_vertices} vertices): {', '.join(bad)}", path)
    return out


def _mocap(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_dir, atomic_path
    from keyshape.retarget.mocap.drive import drive_mesh
    from keyshape.base.formats.markers import read_markers
    from keyshape.base.formats.obj import read_obj, write_obj

    take = read_markers(args.markers, duplicates=args.duplicate_labels)
    mesh = read_obj(args.target, require_faces=True)
    tm = read_target_markers(args.target_markers, mesh.n_vertices, mesh.vertices)
    rigid = None
    if args.rigid:
        text = Path(args.rigid[1:]).read_text() if args.rigid.startswith("@") else args.rigid
        rigid = [s.strip() for s in text.replace("\n", ",").split(",") if s.strip()]
    axes = {"x": ((1, 0, 0), (0, 0, 1)), "y": ((0, 1, 0), (0, 0, 1)), "z": ((0, 0, 1), (0, -1, 0))}
    up, fw = axes[args.up]
    regions = None
    used = [s for s in take.labels if s in tm]
    if args.masks:
        from keyshape.retarget.mocap.masks import read_masks

        if args.method != "planar":
            raise InputError("--masks applies to --method planar only")
        regions = read_masks(args.masks, used, vertices=mesh.vertices,
                             markers=np.array([tm[s] for s in used]), mesh=mesh, up=up, forward=fw)
    res = drive_mesh(take.positions, take.labels, mesh.vertices, tm, method=args.method, rigid_names=rigid,
                     regions=regions, max_gap=args.max_gap, radius_scale=args.radius, up=up, forward=fw)
    print(f"{take.n_frames} frames at {take.rate:g} Hz, {take.n_markers} markers ({take.units}); "
          f"{len(res.labels)} drive the target; rigid set: {', '.join(res.rigid)}")
    print(res.gaps)
    if res.rebuilt:
        print(f"rebuilt from neighbours (never seen): {', '.join(res.rebuilt)}")
    if res.triangulation is not None:
        print(res.triangulation.report())
    for n in res.notes:
        print(n)
    out = Path(args.output)
    verts = res.vertices
    if out.suffix.lower() == ".npz":
        with atomic_path(out) as tmp:
            np.savez(tmp, vertices=verts.astype(np.float32), markers=res.markers, labels=np.array(res.labels),
                     rate=take.rate, triangles=mesh.triangles)
    elif out.suffix.lower() == ".glb":
        try:
            from keyshape.base.formats.gltf import write_glb
        except ImportError:
            raise InputError(".glb output needs retarget.gltf (not in this build): use .npz or an OBJ folder") from None
        base = verts[0]
        d = (verts - base).reshape(len(verts), -1)
        u, s, vt = np.linalg.svd(d, full_matrices=False)
        k = min(args.components, len(s))
        energy = float((s[:k] ** 2).sum() / max((s ** 2).sum(), 1e-300))
        write_glb(out, base, mesh.triangles, vt[:k].reshape(k, -1, 3) * s[:k, None, None],
                  [f"pc{i:02d}" for i in range(k)], weights=u[:, :k], fps=take.rate)
        print(f"{k} principal morph targets keep {100 * energy:.3f}% of the motion energy")
    else:
        with atomic_dir(out) as tmp:
            for f in range(len(verts)):
                write_obj(tmp / f"frame_{f:06d}.obj", mesh, verts[f])
    print(f"wrote {out}")
    return 0
