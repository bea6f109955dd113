"""``keyshape retarget``: replay key-shape weights on the artist's target key shapes (paper 004, section 5)."""
from __future__ import annotations

import argparse



def register(subparsers) -> None:
    """Add ``retarget`` to ``subparsers``."""
    from keyshape.retarget import defaults as A

    p = subparsers.add_parser(
        "retarget", help="drive the artist's target key shapes with decomposed weights (.glb/.usd/.csv/OBJ/video)",
        description="Blend target key shapes (OBJ meshes of one topology, or 2D .pts/JSON drawings) with "
                    "per-frame key-shape weights (delta from the neutral where one is given or found, else the "
                    "paper's absolute form); write .glb, USD (.usda/.usdc/.usd, centimetres), .csv, a folder of "
                    "OBJ/PNG frames or a video. Target files are matched to the weight columns by name.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("weights", help="weights CSV: frame,REGION_K,... (from keyshape decompose)")
    p.add_argument("--targets", nargs="+", metavar="DIR|FILE",
                   help="folder or files of target key shapes (.obj, .pts, .json): one sculpted target per key "
                        "(the paper's route); or use --poses with --rig")
    p.add_argument("--poses", help="POSES.json from keyshape pose: drive an existing blendshape rig (--rig) "
                                   "and write the rig's own curves")
    p.add_argument("--rig", nargs="+", metavar="DIR|FILE",
                   help="with --poses: the rig, a folder of shape OBJs (or a list of OBJ files); its neutral is "
                        "--neutral or the folder's neutral.*/generic_neutral_mesh.obj")
    p.add_argument("--neutral", help="neutral mesh/drawing (needed for --form delta; base of the .glb)")
    p.add_argument("--regions", help="region vertex groups: JSON {region: [vertex indices] | 'OBJ group'} "
                                     "or an OBJ with groups; columns REGION_K use region REGION; 'auto': from "
                                     "the targets' own support (each vertex to the region whose targets move "
                                     "it most)")
    p.add_argument("--tracks", help="tracks CSV: the head motion (root transform: the 3D head), with --rig the "
                                    "pupils' gaze, and the frame rate (else the weights' own, else 30)")
    p.add_argument("--gaze", choices=A.GAZES, default=A.GAZE,
                   help="with --rig and --tracks, the pupils' gaze: angles (the Live Link eye angles), shapes (also "
                        "the rig's eyeLook* shapes; on ICT-FaceKit they move the lids too) or none")
    p.add_argument("--landmarks", default=None,
                   help="with --rig and --tracks: rig landmark JSON, for the head translation's units (the rig's "
                        "inter-ocular distance over the actor's; default: the shipped one for ICT-FaceKit rigs)")
    p.add_argument("--livelink", action="store_true", help=".csv in the Live Link Face layout (ARKit names)")
    p.add_argument("-o", "--output", required=True,
                   help="OUT.glb | OUT.usda/.usdc/.usd | OUT.csv | OUT.mp4 | folder (OBJ frames for meshes, PNG "
                        "frames for drawings)")
    p.add_argument("--overwrite", action="store_true",
                   help="write frames into a non-empty folder keyshape did not make (only its own "
                        "frame_NNNNNN files are written; nothing is deleted)")
    p.add_argument("--accept-partial", action="store_true",
                   help="read --tracks that an interrupted 'keyshape track' marked partial")
    p.set_defaults(func=run)


def run(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.files import check_output_dir
    from keyshape.base.formats.weights import read_weights
    from keyshape.retarget.api import fit_retargeter
    from keyshape.retarget.output.export import ExportOptions, export

    if not (args.targets or args.poses or args.rig):
        raise InputError("give --targets (one target per key) or --poses POSES.json --rig RIG")
    from pathlib import Path as _P
    if _P(args.output).suffix.lower() in (".usda", ".usdc", ".usd"):
        from keyshape.base.formats.usd import require_usd
        require_usd()
    if _P(args.output).suffix == "" or _P(args.output).is_dir():    # a file output: checked by keyshape.declare
        check_output_dir(args.output)
    if args.poses or args.rig:
        return run_rig(args)
    weights = read_weights(args.weights)
    frames, columns = weights.frames, weights.names
    rt = fit_retargeter(columns, args.targets, args.regions, neutral=args.neutral)
    if args.regions == "auto":
        print("keyshape retarget: regions from the targets' own support: " + ", ".join(rt.region_names_ or []))
    ts = rt.targets_
    head, fps, _ = _head(args, weights)
    info = export(args.output, rt, frames, weights.weights, fps=fps, head=head,
                  options=ExportOptions(livelink=args.livelink))
    print(f"keyshape retarget: {len(frames)} frames x {len(columns)} key shapes onto {ts.n_vertices} "
          f"{'vertices' if ts.dim == 3 else 'points'} ({rt.form_} form"
          f"{', regions ' + '+'.join(rt.region_names_) if rt.region_names_ else ''}) at {fps:g} fps"
          f" -> {info['path']} ({info['kind']})")
    return 0


def run_rig(args) -> int:
    """``retarget --poses POSES.json --rig RIG``: the rig's own curves from key weights."""
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.poses import read_poses
    from keyshape.base.formats.weights import read_weights
    from keyshape.retarget.api import rig_curves
    from keyshape.retarget.rig.model import load_rig
    from keyshape.retarget.output.rig_export import export_rig

    if not (args.poses and args.rig):
        raise InputError("--poses and --rig go together (drive a rig with a pose library)")
    if args.targets:
        raise InputError("--targets is for one sculpted target per key; with --poses give --rig only")
    weights = read_weights(args.weights)
    frames, columns = weights.frames, weights.names
    needs_mesh = not str(args.output).lower().endswith(".csv")
    rig = load_rig(args.rig, args.neutral, with_mesh=needs_mesh)
    lib = read_poses(args.poses, rig.names)
    pose_model = (lib.get("keys") or {}).get("model") if isinstance(lib.get("keys"), dict) else None
    if pose_model and args.tracks:
        from keyshape.base.formats.tracks import read_tracks
        tracks_model = read_tracks(args.tracks, accept_partial=args.accept_partial).meta.get("model")
        if tracks_model and tracks_model != pose_model:
            raise InputError(f"the pose library was fitted to keys of another tracker model ({pose_model}; "
                             f"the tracks {args.tracks}: {tracks_model}): its poses are another actor's "
                             "key shapes. Fit a pose library to this model's keys ('keyshape pose')", args.poses)
    curves = rig_curves(weights.weights, columns, lib, rig, args.poses)
    head, fps, src = _head(args, weights, rig)
    eyes = None
    if src is not None:
        from keyshape.retarget.api import apply_gaze
        curves, eyes = apply_gaze(curves, rig, src[0], frames, src[1], args.tracks, gaze=args.gaze)
    info = export_rig(args.output, rig, frames, curves, fps=fps, head=head, livelink=args.livelink,
                      eyes=eyes)
    used = int((np.abs(curves).max(axis=0) > 0).sum())
    print(f"keyshape retarget: {len(frames)} frames x {len(columns)} key weights -> {used} of {rig.n_shapes} rig "
          f"shapes moving at {fps:g} fps -> {info['path']} ({info['kind']})")
    return 0


def _head(args, weights, rig=None):
    """Head motion from ``--tracks`` (or None), the frame rate (the tracks', else the weights' own, else 30) and, with
    ``--tracks``, ``(tracks, head kind)`` for the gaze (else None): :func:`keyshape.retarget.api.take_motion` with
    the command's defaults."""
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.weights import read_weights_fps
    from keyshape.retarget.api import RetargetOptions, take_motion

    tr = read_tracks(args.tracks, accept_partial=args.accept_partial) if args.tracks else None
    head, fps, kind = take_motion(tr, weights.frames, read_weights_fps(args.weights), rig,
                                  RetargetOptions(landmarks=args.landmarks), args.tracks,
                                  say=lambda line: print(f"keyshape retarget: {line}"))
    return head, fps, None if tr is None else (tr, kind)
