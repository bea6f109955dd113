"""``keyshape solve``: the rig's curves of every frame solved straight from the tracks (no pose library)."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    """Add ``solve`` to ``subparsers``."""
    from keyshape.retarget import defaults as A

    p = subparsers.add_parser(
        "solve", help="drive an existing blendshape rig: its curves solved frame by frame from the tracks",
        description="For every frame, non-negative, sparse, left-right symmetric weights of the rig's shapes "
                    "(within their range) whose projected landmark motion matches the actor's head-stabilised "
                    "motion from the neutral that KEYS.json records (keyshape select), each eye calibrated so the "
                    "take's deepest closure closes the rig's eye and each brow so its ends rise as far as the "
                    "actor's. Writes the rig's curves: CSV with the rig's "
                    "names, Live Link Face CSV (--livelink) or a .glb with the rig's shapes. With --poses and "
                    "--weights, the artist's pose library overrides the solve at its keys.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("tracks", help="tracks CSV (keyshape track)")
    p.add_argument("--keys", required=True,
                   help="KEYS.json from keyshape select: the head stabilisation, the regions and the actor's neutral")
    p.add_argument("--rig", nargs="+", required=True, metavar="DIR|FILE",
                   help="rig: folder of shape OBJs (or a list of OBJ files) of one topology")
    p.add_argument("--neutral", default=None,
                   help="the rig's neutral OBJ (default: the folder's neutral.* or generic_neutral_mesh.obj)")
    p.add_argument("--landmarks", default=None,
                   help="rig landmarks: a keyshape-rig-landmarks JSON, or the rig's iBUG-68 vertex list (a JSON list or one "
                        "index a line) (default: the shipped correspondence for ICT-FaceKit rigs, else found on "
                        "the rig and written beside the output, OUT.landmarks.json)")
    p.add_argument("--sparsity", type=float, default=A.SOLVE_SPARSITY,
                   help="L1 weight (dimensionless): larger gives fewer shapes per frame")
    p.add_argument("--symmetry", type=float, default=A.SOLVE_SYMMETRY,
                   help="weight (dimensionless) of the left-right prior: mirrored shapes (_L/_R) kept alike "
                        "unless the actor's two sides differ")
    p.add_argument("--smooth", type=float, default=A.SOLVE_SMOOTH, help="temporal smoothness (dimensionless; 0: none)")
    p.add_argument("--no-calibrate", dest="calibrate", action="store_false",
                   help="do not scale each eye's lid motion so that the take's deepest closure closes the rig's eye, "
                        "nor the brow shapes so that the brow ends rise as far as the actor's")
    p.add_argument("--keep-rest", dest="rest_offset", action="store_false", default=A.SOLVE_REST_OFFSET,
                   help="take the actor's rest from KEYS.json as it is (default: its error, one offset of its points' "
                        "left-right symmetric heights, lids excepted, shared by all frames, is solved with the "
                        "curves, so a rest frame that was not relaxed does not offset every frame)")
    p.add_argument("--keep-yaw-slide", dest="yaw_slide", action="store_false", default=A.SOLVE_YAW_SLIDE,
                   help="keep the mouth's sideways parallax under head yaw (default: with a 2D head, the mouth's "
                        "antisymmetric motion that follows the 3D head's yaw over the take is taken out before the "
                        "solve, so a head turn does not read as mouthLeft/Right)")
    p.add_argument("--keep-yaw-stretch", dest="yaw_stretch", action="store_false", default=A.SOLVE_YAW_STRETCH,
                   help="keep the mouth's vertical stretch under head yaw (default: with a 2D head stabilised on the eye "
                        "corners, the mouth's heights from the eye line are brought back from the 1/cos(yaw) the "
                        "stabilisation stretches them by, so a turned head does not read as an open jaw)")
    p.add_argument("--pitch-parallax", action="store_true", default=A.SOLVE_PITCH_PARALLAX,
                   help="with a 2D head, take out of the mouth's motion the vertical parallax the 3D head's pitch gives its "
                        "points at the rig's depths, so a nod does not read as a smile or a frown")
    p.add_argument("--poses", default=None,
                   help="POSES.json (keyshape pose, corrected by hand): with --weights, each key's rig pose is "
                        "what the rig shows at that key; the difference from the solve there is added in "
                        "proportion to the key's weight in every frame")
    p.add_argument("--weights", default=None, help="WEIGHTS.csv (keyshape decompose) for --poses")
    p.add_argument("--livelink", action="store_true", help=".csv in the Live Link Face layout (ARKit names)")
    p.add_argument("--fps", type=float, default=None, help="frame rate (default: from the tracks' timestamps, else 30)")
    p.add_argument("--head-units", type=float, default=None,
                   help="mesh units per tracker model unit for the head translation (default: the rig's "
                        "inter-ocular distance over the actor's)")
    p.add_argument("--reference-frame", type=int, default=None,
                   help="tracks frame taken as the rest head pose (default: with the 3D head, the actor's most "
                        "front-facing relaxed frame; with a 2D head, the first frame)")
    p.add_argument("--head-pose", choices=("3d", "rigid", "tracker"), default=A.HEAD_MOTION,
                   help="the head motion written: 3d (yaw, pitch, roll and translation with depth from the track's "
                        "rigid points on a 3D face) or the 2D motion of rigid|tracker (as keyshape select --head-pose)")
    p.add_argument("--gaze", choices=A.GAZES, default=A.GAZE,
                   help="the pupils' gaze: angles (the Live Link eye angles), shapes (also the rig's eyeLook* "
                        "shapes, held fixed in the solve; on ICT-FaceKit they move the lids too) or none")
    p.add_argument("--gaze-lids", action="store_true", default=A.SOLVE_GAZE_LIDS,
                   help="solve the lids with the pupils and the rig's eyeLook* shapes (each at most what the pupils "
                        "show, held half a second), so the lid motion of a look down is not read as a blink "
                        "(eyeLook* written only with --gaze shapes)")
    p.add_argument("-o", "--output", required=True, help="OUT.csv | OUT.glb")
    p.add_argument("--overwrite", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--accept-partial", action="store_true",
                   help="read tracks that an interrupted 'keyshape track' marked partial")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.files import check_output
    from keyshape.base.formats.keys import read_keys, read_keys_head_pose
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.retarget.api import check_solve_options, solve_rig
    from keyshape.retarget.rig import load_rig
    from keyshape.retarget.rig_export import export_rig

    check_solve_options(args.sparsity, args.symmetry, args.smooth)
    if bool(args.poses) != bool(args.weights):
        raise InputError("--poses and --weights go together (the artist's pose library and the key weights)")
    inputs = [f for f in (args.tracks, args.keys, args.neutral, args.landmarks, args.poses, args.weights) if f]
    check_output(args.output, "file", inputs)
    scheme_name, n_points, regions = read_keys(args.keys)
    tracks = read_tracks(args.tracks, accept_partial=args.accept_partial)
    if tracks.n_points != n_points:
        raise InputError(f"the tracks have {tracks.n_points} points, the keys' scheme {scheme_name} {n_points}",
                         args.tracks)
    needs_mesh = not str(args.output).lower().endswith(".csv")
    rig = load_rig(args.rig if len(args.rig) > 1 else args.rig[0], args.neutral, with_mesh=needs_mesh)
    from keyshape.retarget.landmarks_cli import resolve_landmarks
    args.landmarks = resolve_landmarks(rig, scheme_name, args.landmarks, args.output)
    report: dict = {}
    curves, head, fps, eyes = solve_rig(
        tracks, regions, scheme_name, read_keys_head_pose(args.keys), rig, landmarks=args.landmarks,
        sparsity=args.sparsity, symmetry=args.symmetry, smooth=args.smooth, calibrate=args.calibrate,
        rest_offset=args.rest_offset,
        gaze=args.gaze, head=args.head_pose, reference_frame=args.reference_frame, head_units=args.head_units,
        fps=args.fps, source=args.tracks, gaze_lids=args.gaze_lids, yaw_slide=args.yaw_slide,
        pitch_parallax=args.pitch_parallax, yaw_stretch=args.yaw_stretch, report=report)
    for line in calibration_lines(report):
        print(f"keyshape: {line}")
    if args.poses:
        curves = _override(args, curves, tracks.frame, rig, regions)
    info = export_rig(args.output, rig, tracks.frame, curves, fps=fps, head=head, livelink=args.livelink,
                      overwrite=args.overwrite, inputs=inputs, eyes=eyes)
    used = int((np.abs(curves).max(axis=0) > 0).sum())
    print(f"keyshape solve: {len(curves)} frames -> {used} of {rig.n_shapes} rig shapes moving at {fps:g} fps "
          f"-> {info['path']} ({info['kind']})")
    return 0


def calibration_lines(report: dict) -> list[str]:
    """What the solve's calibrations did (:func:`keyshape.retarget.solve.solve_curves`' ``report``), for the
    animator: each eye's deepest closure and how far its lids' travel was scaled, the brow shapes' scales."""
    lines = [e.describe() for e in report.get("eyes", [])]
    brows = report.get("brows", {})
    if brows:
        lines.append("brows: curves scaled so the brow ends rise as far as the actor's: "
                     + ", ".join(f"{n} x{g:.2f}" for n, g in sorted(brows.items())))
    if lines:
        lines[-1] += " (--no-calibrate keeps the tracked sizes)"
    return lines


def _override(args, curves, frames, rig, regions):
    """The artist's pose library over the solve (:func:`keyshape.retarget.api.override_poses`)."""
    from keyshape.base.formats.poses import read_poses
    from keyshape.base.formats.weights import read_weights
    from keyshape.retarget.api import override_poses

    wf, columns, weights, _ = read_weights(args.weights)
    return override_poses(curves, frames, regions, weights, columns, wf, read_poses(args.poses, rig.names), rig,
                          args.poses, args.weights)
