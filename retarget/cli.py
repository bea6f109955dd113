"""``keyshape retarget``: replay key-shape weights on the artist's target key shapes (paper 004, section 5)."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    """Add ``retarget`` to ``subparsers``."""
    p = subparsers.add_parser(
        "retarget", help="drive the artist's target key shapes with decomposed weights (.glb/.csv/OBJ/video)",
        description="Blend target key shapes (OBJ meshes of one topology, or 2D .pts/JSON drawings) with "
                    "per-frame key-shape weights; write .glb, .csv, a folder of OBJ/PNG frames or a video.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("weights", help="weights CSV: frame,REGION_K,... (from keyshape decompose)")
    p.add_argument("--targets", nargs="+", required=True, metavar="DIR|FILE",
                   help="folder or files of target key shapes (.obj, .pts, .json)")
    p.add_argument("--map", dest="mapping", help='mapping JSON {"REGION_K": "target file"} '
                                                 "(default: match column names to file stems)")
    p.add_argument("--neutral", help="neutral mesh/drawing (needed for --form delta; base of the .glb)")
    p.add_argument("--form", choices=("auto", "absolute", "delta"), default="auto",
                   help="delta: N + sum w_i (B_i - N), for weights fitted relative to a neutral (keyshape "
                        "decompose's, relative to the sequence's mean shape); absolute: sum w_i B_i (the paper's "
                        "literal form); auto: delta when a neutral is given or found, else absolute")
    p.add_argument("--regions", help="region vertex groups: JSON {region: [vertex indices] | 'OBJ group'} "
                                     "or an OBJ with groups; columns REGION_K use region REGION")
    p.add_argument("--band", type=float, default=None,
                   help="region blending band width in mesh units (default 10%% of the bounding-box diagonal)")
    p.add_argument("--metric", choices=("geodesic", "euclidean"), default="geodesic",
                   help="distance for the region band")
    p.add_argument("--tracks", help="tracks CSV: its 2D pose gives the head motion (root transform)")
    p.add_argument("--reference-frame", type=int, default=0, help="tracks frame taken as the rest head pose")
    p.add_argument("--head-units", type=float, default=1.0,
                   help="mesh units per tracker model unit, scales the head translation")
    p.add_argument("--bake-head", action="store_true", help="apply head motion to OBJ/PNG/video frames")
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate (default: from the tracks' timestamps, else 30)")
    p.add_argument("--clamp", action="store_true", help="clamp weights to [0, 1] in .glb/.csv (default keep)")
    p.add_argument("--livelink", action="store_true", help=".csv in the Live Link Face layout (ARKit names)")
    p.add_argument("--scheme", help="landmark scheme to draw 2D targets (default: by point count)")
    p.add_argument("-o", "--output", required=True,
                   help="OUT.glb | OUT.csv | OUT.mp4 | folder (OBJ frames for meshes, PNG frames for drawings)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.retarget.export import export
    from keyshape.retarget.retargeter import Retargeter
    from keyshape.retarget.targets import load_targets, read_regions
    from keyshape.base.formats.weights import read_weights

    frames, columns, weights = read_weights(args.weights)
    targets = args.targets[0] if len(args.targets) == 1 else args.targets
    ts = load_targets(columns, targets, mapping=args.mapping, neutral=args.neutral)
    regions = read_regions(args.regions, ts.mesh) if args.regions else None
    rt = Retargeter(form=args.form, band=args.band, metric=args.metric).fit(ts, regions, args.regions or "regions")
    head, fps = None, args.fps
    if args.tracks:
        from keyshape.retarget.headpose import head_motion
        from keyshape.base.formats.tracks import read_tracks
        tr = read_tracks(args.tracks)
        pos = {int(f): i for i, f in enumerate(tr.frame)}
        missing = [int(f) for f in frames if int(f) not in pos]
        if missing:
            raise InputError(f"weights frames {missing[:5]} are not in the tracks", args.tracks)
        rows = np.array([pos[int(f)] for f in frames])
        if args.reference_frame not in pos:
            raise InputError(f"reference frame {args.reference_frame} is not in the tracks", args.tracks)
        from keyshape.retarget.headpose import hold_invalid
        full = hold_invalid(tr.pose, tr.success)
        pose = np.concatenate([full[rows], full[[pos[args.reference_frame]]]])
        head = head_motion(pose, reference=len(rows), units_per_model=args.head_units)
        head = type(head)(head.translation[:-1], head.rotation[:-1], head.scale[:-1], head.angle[:-1])
        if fps is None and len(tr.time) > 1:
            dt = np.diff(tr.time)
            dt = dt[np.isfinite(dt) & (dt > 0)]
            fps = round(float(1.0 / np.median(dt)), 3) if len(dt) else None
    fps = fps or 30.0
    info = export(args.output, rt, frames, weights, fps=fps, head=head, clamp=args.clamp, livelink=args.livelink,
                  bake_head=args.bake_head, scheme=args.scheme)
    extra = f", {info['n_clamped']} weights clamped to [0, 1]" if args.clamp else ""
    print(f"keyshape retarget: {len(frames)} frames x {len(columns)} key shapes onto {ts.n_vertices} "
          f"{'vertices' if ts.dim == 3 else 'points'} ({rt.form_} form"
          f"{', regions ' + '+'.join(rt.region_names_) if rt.region_names_ else ''}) at {fps:g} fps"
          f"{extra} -> {info['path']} ({info['kind']})")
    return 0
