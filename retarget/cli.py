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
    p.add_argument("--overwrite", action="store_true",
                   help="write frames into a non-empty folder keyshape did not make (only its own "
                        "frame_NNNNNN files are written; nothing is deleted)")
    p.add_argument("--accept-partial", action="store_true",
                   help="read --tracks that an interrupted 'keyshape track' marked partial")
    p.set_defaults(func=run)


def _input_files(args) -> list:
    """Every file this run reads (an output may be none of them)."""
    from pathlib import Path

    files = [args.weights, args.mapping, args.neutral, args.regions, args.tracks]
    for t in args.targets:
        p = Path(t)
        files += list(p.iterdir()) if p.is_dir() else [p]
        if p.is_dir():
            files.append(p)
    return [f for f in files if f is not None]


def run(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.weights import read_weights
    from keyshape.retarget.api import fit_retargeter, head_from_tracks
    from keyshape.retarget.export import export
    from keyshape.base.files import check_output, check_output_dir

    for name, v, lo in (("--head-units", args.head_units, 0.0), ("--fps", args.fps, 0.0), ("--band", args.band, 0.0)):
        if v is not None and not (np.isfinite(v) and lo < v < 1e9):
            raise InputError(f"{name} {v}: must be a finite number > {lo:g}")
    if args.reference_frame < 0:
        raise InputError(f"--reference-frame {args.reference_frame}: frames are numbered from 0")
    inputs = _input_files(args)
    from pathlib import Path as _P
    out_is_dir = _P(args.output).suffix == "" or _P(args.output).is_dir()
    if out_is_dir:
        check_output_dir(args.output, args.overwrite, inputs)
    else:
        check_output(args.output, "file", inputs)
    frames, columns, weights, _ = read_weights(args.weights)
    rt = fit_retargeter(columns, args.targets, args.regions, mapping=args.mapping, neutral=args.neutral,
                        form=args.form, band=args.band, metric=args.metric)
    ts = rt.targets_
    head, fps = None, args.fps
    if args.tracks:
        from keyshape.base.formats.tracks import read_tracks

        head, tracks_fps = head_from_tracks(read_tracks(args.tracks, accept_partial=args.accept_partial), frames,
                                            args.reference_frame, args.head_units, args.tracks)
        fps = fps or tracks_fps
    fps = fps or 30.0
    info = export(args.output, rt, frames, weights, fps=fps, head=head, clamp=args.clamp, livelink=args.livelink,
                  bake_head=args.bake_head, scheme=args.scheme, overwrite=args.overwrite, inputs=inputs)
    extra = f", {info['n_clamped']} weights clamped to [0, 1]" if args.clamp else ""
    print(f"keyshape retarget: {len(frames)} frames x {len(columns)} key shapes onto {ts.n_vertices} "
          f"{'vertices' if ts.dim == 3 else 'points'} ({rt.form_} form"
          f"{', regions ' + '+'.join(rt.region_names_) if rt.region_names_ else ''}) at {fps:g} fps"
          f"{extra} -> {info['path']} ({info['kind']})")
    return 0
