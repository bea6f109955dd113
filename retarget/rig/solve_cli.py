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
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        epilog="The solve's priors (sparsity, symmetry, smoothness) are keyshape.api.solve's SolveOptions.")
    p.add_argument("tracks", help="tracks CSV (keyshape track)")
    p.add_argument("--keys", required=True,
                   help="KEYS.json from keyshape select: the head stabilisation, the regions and the actor's neutral")
    from keyshape.retarget.rig.pose_cli import add_rig_options

    add_rig_options(p)
    p.add_argument("--poses", default=None,
                   help="POSES.json (keyshape pose, corrected by hand): with --weights, each key's rig pose is "
                        "what the rig shows at that key; the difference from the solve there is added in "
                        "proportion to the key's weight in every frame")
    p.add_argument("--weights", default=None, help="WEIGHTS.csv (keyshape decompose) for --poses")
    p.add_argument("--livelink", action="store_true", help=".csv in the Live Link Face layout (ARKit names)")
    p.add_argument("--gaze", choices=A.GAZES, default=A.GAZE,
                   help="the pupils' gaze: angles (the Live Link eye angles), shapes (also the rig's eyeLook* "
                        "shapes, held fixed in the solve; on ICT-FaceKit they move the lids too) or none")
    p.add_argument("-o", "--output", required=True, help="OUT.csv | OUT.glb")
    p.add_argument("--overwrite", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--accept-partial", action="store_true",
                   help="read tracks that an interrupted 'keyshape track' marked partial")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import read_keys, read_keys_head_pose
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.decompose.take import Take
    from keyshape.retarget.api import solve_rig
    from keyshape.retarget.defaults import SolveOptions
    from keyshape.retarget.rig.model import load_rig
    from keyshape.retarget.output.rig_export import export_rig

    if bool(args.poses) != bool(args.weights):
        raise InputError("--poses and --weights go together (the artist's pose library and the key weights)")
    scheme_name, n_points, regions = read_keys(args.keys)
    tracks = read_tracks(args.tracks, accept_partial=args.accept_partial)
    from keyshape.base.formats.keys import check_keys_model
    check_keys_model(args.keys, tracks.meta.get("model"), False)
    if tracks.n_points != n_points:
        raise InputError(f"the tracks have {tracks.n_points} points, the keys' scheme {scheme_name} {n_points}",
                         args.tracks)
    needs_mesh = not str(args.output).lower().endswith(".csv")
    rig = load_rig(args.rig, args.neutral, with_mesh=needs_mesh)
    from keyshape.retarget.rig.landmarks_cli import resolve_landmarks
    args.landmarks = resolve_landmarks(rig, scheme_name, args.landmarks, args.output)
    report: dict = {}
    curves, head, fps, eyes = solve_rig(Take.fit(tracks, args.tracks), regions, scheme_name,
                                        read_keys_head_pose(args.keys), rig,
                                        SolveOptions(gaze=args.gaze, landmarks=args.landmarks), report=report)
    for line in calibration_lines(report):
        print(f"keyshape: {line}")
    if args.poses:
        curves = _override(args, curves, tracks.frame, rig, regions)
    info = export_rig(args.output, rig, tracks.frame, curves, fps=fps, head=head, livelink=args.livelink,
                      eyes=eyes)
    used = int((np.abs(curves).max(axis=0) > 0).sum())
    print(f"keyshape solve: {len(curves)} frames -> {used} of {rig.n_shapes} rig shapes moving at {fps:g} fps "
          f"-> {info['path']} ({info['kind']})")
    return 0


def calibration_lines(report: dict) -> list[str]:
    """What the solve's calibrations did (:meth:`keyshape.retarget.rig.solve.RigSolver.fit`'s ``report``), for the
    animator: each eye's deepest closure and how far its lids' travel was scaled, the brow shapes' scales."""
    lines = [e.describe() for e in report.get("eyes", [])]
    brows = report.get("brows", {})
    if brows:
        lines.append("brows: curves scaled so the brow ends rise as far as the actor's: "
                     + ", ".join(f"{n} x{g:.2f}" for n, g in sorted(brows.items())))
    return lines


def _override(args, curves, frames, rig, regions):
    """The artist's pose library over the solve (:func:`keyshape.retarget.api.override_poses`)."""
    from keyshape.base.formats.poses import read_poses
    from keyshape.base.formats.weights import read_weights
    from keyshape.retarget.api import override_poses

    wf, columns, weights, _ = read_weights(args.weights)
    return override_poses(curves, frames, regions, weights, columns, wf, read_poses(args.poses, rig.names), rig,
                          args.poses, args.weights)
