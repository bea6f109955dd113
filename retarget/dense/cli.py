"""``keyshape register``, ``keyshape keypoints`` and ``keyshape transfer``: dense-mesh tools."""
from __future__ import annotations

from pathlib import Path

#: control vertices of ``keyshape register``'s fit (``register_mesh(n_controls=...)`` for another)
CONTROLS = 200
#: N_k, the random target key points of eqs. 7-9 in ``keyshape transfer`` (``transfer_sequence(n_samples=...)``)
SAMPLES = 6000


def register(subparsers) -> None:
    """Add this stage's subcommands to ``subparsers``."""
    p = subparsers.add_parser("register", help="fit a reference face mesh onto a target mesh (001 section 6)",
                              description="Fit REFERENCE.obj onto TARGET.obj from 10-12 landmark pairs: RBF warp, "
                                          "then minimise distance + strain + bending energy; optionally carry "
                                          "markers and discontinuity masks onto the target.")
    p.add_argument("reference")
    p.add_argument("target")
    p.add_argument("--landmarks", required=True, help="PAIRS.json: [{\"reference\": R, \"target\": T}, ...]")
    p.add_argument("-o", "--output", required=True, help="FITTED.obj: the reference topology fitted to the target")
    p.add_argument("--markers", help="reference markers JSON {name: vertex index or [x, y, z]}")
    p.add_argument("--out-markers", help="where to write the markers placed on the target")
    p.add_argument("--masks", help="reference masks JSON {name: [vertex index, ...]}")
    p.add_argument("--out-masks", help="where to write the masks as target vertex groups")
    p.set_defaults(func=_register)

    p = subparsers.add_parser("keypoints", help="insert key points into a dense sequence (002 section 5)")
    p.add_argument("sequence", help="SEQUENCE.npz with vertices (n_frames, n_points, 3)")
    p.add_argument("--initial", required=True,
                   help="number K of initial key points (farthest-point sampled) or a KEYPOINTS.json")
    p.add_argument("-o", "--output", required=True, help="KEYPOINTS.json")
    p.add_argument("--no-correspondence", action="store_true",
                   help="frames do not share point order: nearest-point errors and local registration")
    p.set_defaults(func=_keypoints)

    p = subparsers.add_parser("transfer", help="transfer a dense sequence onto another face (002 section 6)")
    p.add_argument("sequence", help="SEQUENCE.npz (frame 0 neutral)")
    p.add_argument("--target", required=True, help="target neutral MESH.obj")
    p.add_argument("--keypoints", help="KEYPOINTS.json on the source (default: 68 farthest-point samples)")
    p.add_argument("--landmarks", help="PAIRS.json mapping source vertices (reference) to the target; "
                                       "default: same vertex indices (same topology)")
    p.add_argument("-o", "--output", required=True, help="OUT.npz (vertices, faces of the target)")
    p.set_defaults(func=_transfer)


def _check_markers(markers, n_vertices: int, path) -> None:
    """Refuse marker vertex indices outside the mesh and non-finite or implausible positions."""
    import numpy as np

    from keyshape.base.errors import InputError

    for k, m in (markers or {}).items():
        if isinstance(m, int):
            if not 0 <= m < n_vertices:
                raise InputError(f"marker {k!r}: vertex {m} does not exist (0..{n_vertices - 1})", path)
        elif not np.all(np.isfinite(m)) or np.abs(m).max() > 1e7:
            raise InputError(f"marker {k!r}: position {m} is not finite or implausibly far", path)


def _check_masks(masks, n_vertices: int, path) -> None:
    import numpy as np

    from keyshape.base.errors import InputError

    for k, idx in (masks or {}).items():
        idx = np.asarray(idx)
        if idx.size and (idx.min() < 0 or idx.max() >= n_vertices):
            raise InputError(f"mask {k!r}: vertex indices outside 0..{n_vertices - 1}", path)


def _register(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.formats.markers import read_mesh_markers, write_mesh_markers
    from keyshape.base.formats.masks import read_masks, write_masks
    from keyshape.base.formats.pairs import read_pairs
    from keyshape.retarget.dense.registration import place_markers, register_mesh, transfer_masks
    from keyshape.base.formats.obj import read_obj, write_obj

    if bool(args.markers) != bool(args.out_markers):
        raise InputError("--markers and --out-markers go together")
    if bool(args.masks) != bool(args.out_masks):
        raise InputError("--masks and --out-masks go together")
    ref = read_obj(args.reference, require_faces=True)
    tgt = read_obj(args.target, require_faces=True)
    pairs = read_pairs(args.landmarks)
    markers = read_mesh_markers(args.markers) if args.markers else None
    masks = read_masks(args.masks) if args.masks else None
    if masks is not None and not masks.vertex_lists():
        raise InputError("no region lists 'vertices' (image and vertex-group regions need no carrying)", args.masks)
    _check_markers(markers, ref.n_vertices, args.markers)
    _check_masks(masks.vertex_lists() if masks is not None else None, ref.n_vertices, args.masks)
    res = register_mesh(ref.vertices, ref.triangles, tgt.vertices, tgt.triangles, pairs,
                        n_controls=CONTROLS, source=args.landmarks)
    # every output computed before any is written: a failure writes nothing
    placed = None if markers is None else place_markers(markers, ref.vertices, ref.triangles, res.vertices,
                                                        tgt.vertices, tgt.triangles, source=args.markers)
    carried = None if masks is None else transfer_masks(masks.vertex_lists(), res.vertices, tgt.vertices, args.masks)
    write_obj(args.output, ref, res.vertices)
    if placed is not None:
        write_mesh_markers(args.out_markers, placed)
    if carried is not None:
        write_masks(args.out_masks, masks.with_vertex_lists(carried))
    print(f"registered in {res.seconds:.1f} s ({res.solver}, {res.n_evals} evaluations): "
          f"energy {res.energy_start:.3g} -> {res.energy:.3g}; wrote {args.output}")
    return 0


def _initial(spec: str, frames, seed: int):
    import numpy as np

    from keyshape.base.formats.keypoints import read_keypoints
    from keyshape.retarget.dense.keypoints import farthest_point_sample

    if spec.isdigit():
        from keyshape.base.errors import InputError
        if not 1 <= int(spec) <= frames.shape[1]:
            raise InputError(f"--initial {spec}: need 1 to {frames.shape[1]} key points")
        return farthest_point_sample(frames[0], int(spec), np.random.default_rng(seed))
    return read_keypoints(spec, frames.shape[1])


def _keypoints(args) -> int:
    from keyshape.base.formats.keypoints import write_keypoints
    from keyshape.base.formats.sequence import read_sequence
    from keyshape.retarget.dense.keypoints import KeyPointInserter

    frames, _ = read_sequence(args.sequence)
    init = _initial(args.initial, frames, 0)
    ins = KeyPointInserter(correspondence=not args.no_correspondence, rng=0).fit(frames, init)
    write_keypoints(args.output, ins.key_indices_, ins.history_)
    h = ins.history_
    print(f"{len(init)} -> {len(ins.key_indices_)} key points in {len(h) - 1} round(s); "
          f"mean error {h[0]['mean_error']:.4g} -> {h[-1]['mean_error']:.4g}; wrote {args.output}")
    return 0


def _transfer(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.keypoints import read_keypoints
    from keyshape.base.formats.pairs import read_pairs
    from keyshape.base.formats.sequence import read_sequence, write_sequence
    from keyshape.retarget.dense.registration import resolve_landmarks
    from keyshape.retarget.dense.transfer import transfer_sequence
    from keyshape.base.formats.obj import read_obj

    frames, _ = read_sequence(args.sequence)
    tgt = read_obj(args.target, require_faces=True)
    if args.landmarks:
        pairs = read_pairs(args.landmarks)
        _, tk, _ = resolve_landmarks(pairs, frames[0], tgt.vertices, args.landmarks)
        bad = [i for i, p in enumerate(pairs) if not isinstance(p["reference"], int)]
        if bad:
            raise InputError(f"pair {bad[0]}: the source side must be a vertex index for transfer", args.landmarks)
        sk = np.array([p["reference"] for p in pairs], np.intp)
    else:
        if tgt.n_vertices != frames.shape[1]:
            raise InputError(f"target has {tgt.n_vertices} vertices, the sequence {frames.shape[1]} points: "
                             "give --landmarks PAIRS.json to say which points correspond", args.target)
        sk = read_keypoints(args.keypoints, frames.shape[1]) if args.keypoints else _initial("68", frames, 0)
        tk = sk
    out = transfer_sequence(frames, sk, tgt.vertices, tk, n_samples=SAMPLES, rng=0)
    write_sequence(args.output, out, tgt.triangles)
    print(f"transferred {len(out)} frames onto {Path(args.target).name}; wrote {args.output}")
    return 0
