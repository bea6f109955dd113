"""``keyshape pose``: suggest each key shape's pose on an artist's blendshape rig (a pose library)."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    """Add ``pose`` to ``subparsers``."""
    p = subparsers.add_parser(
        "pose", help="suggest a rig pose (rig shape weights) for every key shape -> POSES.json",
        description="For every key of every region of KEYS.json, find non-negative, sparse weights of the rig's "
                    "shapes (within their range) whose projected landmark motion best matches the key's 2D "
                    "motion from the actor's neutral. Correct POSES.json by hand, then "
                    "'keyshape retarget WEIGHTS.csv --poses POSES.json --rig RIG -o OUT'.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("keys", help="KEYS.json from keyshape select")
    p.add_argument("--rig", nargs="+", required=True, metavar="DIR|FILE",
                   help="rig: folder of shape OBJs (or a list of OBJ files) of one topology")
    p.add_argument("--neutral", default=None,
                   help="the rig's neutral OBJ (default: the folder's neutral.* or generic_neutral_mesh.obj)")
    p.add_argument("--landmarks", default=None,
                   help="rig landmark JSON: the rig vertices of the scheme's points (default: the shipped "
                        "correspondence for ICT-FaceKit rigs)")
    p.add_argument("--sparsity", type=float, default=0.01,
                   help="L1 weight (dimensionless): larger gives fewer shapes per pose")
    p.add_argument("--nuisance", choices=("auto", "translation", "similarity", "none"), default="auto",
                   help="region motions fitted freely besides the rig shapes (left by 2D head-pose removal): "
                        "auto = translation of the mouth; for the eyes and brows nothing when the keys' head "
                        "was stabilised on rigid points (select --head-pose rigid), else a similarity")
    p.add_argument("--opposed", type=float, default=-0.5, metavar="COSINE",
                   help="two shapes of a region whose landmark motions have a cosine below this (antagonists: "
                        "browDown and browOuterUp, mouthLeft and mouthRight) are never used in one pose; -1 "
                        "allows every combination")
    p.add_argument("-o", "--output", required=True, help="POSES.json to write")
    p.add_argument("--edit", action="store_true",
                   help="then serve a local page (127.0.0.1) to correct the poses by hand; Ctrl-C stops it")
    p.add_argument("--port", type=int, default=8766, help="port of the --edit page (0: any free port)")
    p.set_defaults(func=run)

    e = subparsers.add_parser(
        "pose-edit", help="correct a POSES.json by hand in a local web page (sliders per rig shape)",
        description="Serve a page on 127.0.0.1 showing each key: the actor's key contour over the neutral "
                    "(from KEYS.json), the rig rendered in the key's pose and one slider per rig shape of the "
                    "key's region. Every change is checked and saved to POSES.json at once. Ctrl-C stops it.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    e.add_argument("poses", help="POSES.json from keyshape pose")
    e.add_argument("--rig", nargs="+", required=True, metavar="DIR|FILE",
                   help="the rig the poses are for: folder of shape OBJs (or a list of OBJ files)")
    e.add_argument("--neutral", default=None, help="the rig's neutral OBJ (default: as for keyshape pose)")
    e.add_argument("--keys", default=None,
                   help="KEYS.json the poses were fitted from (default: the one POSES.json names, if found)")
    e.add_argument("--port", type=int, default=8766, help="port on 127.0.0.1 (0: any free port)")
    e.set_defaults(func=run_edit)


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import read_keys, read_keys_head_pose, read_keys_source
    from keyshape.base.formats.poses import write_poses
    from keyshape.base.schemes import load_scheme
    from keyshape.decompose.regions import available_regions, region_points
    from keyshape.retarget.poses import pose_library
    from keyshape.retarget.rig import load_rig, project, rig_landmarks, shape_regions

    if not (np.isfinite(args.opposed) and -1.0 <= args.opposed <= 0.0):
        raise InputError(f"--opposed {args.opposed}: a cosine from -1 to 0")
    if not (np.isfinite(args.sparsity) and 0.0 <= args.sparsity <= 100.0):
        raise InputError(f"--sparsity {args.sparsity}: a number from 0 to 100")
    scheme_name, n_points, regions = read_keys(args.keys)
    rig = load_rig(args.rig if len(args.rig) > 1 else args.rig[0], args.neutral, with_mesh=False)
    W, lm_path = rig_landmarks(rig, scheme_name, args.landmarks)
    scheme = load_scheme(scheme_name)
    lm_neutral = project(W @ rig.neutral)
    lm_deltas = project(np.einsum("pv,svc->spc", W, rig.deltas, optimize=True))
    groups = {r: region_points(scheme, r) for r in available_regions(scheme)}
    reg_shapes = shape_regions(lm_deltas, groups, names=rig.names)
    stabilized = read_keys_head_pose(args.keys)["method"] in ("rigid", "3d")
    lib = pose_library(regions, rig.names, lm_neutral, lm_deltas, reg_shapes, rig.value_range, args.sparsity,
                       args.nuisance, stabilized, args.opposed)
    fit = lib.pop("_fit")
    data = {"keys": {"file": str(args.keys), "scheme": scheme_name},
            "rig": {"neutral": str(rig.neutral_file), "n_vertices": rig.n_vertices, "shapes": rig.names,
                    "landmarks": str(lm_path)},
            "range": list(rig.value_range), "regions": lib}
    src = read_keys_source(args.keys)
    if src.get("model"):
        data["keys"]["model"] = src["model"]
    write_poses(args.output, data)
    for r, reg in lib.items():
        if r == "pupils" and r in groups:
            moving = [j for j, n in enumerate(rig.names) if n in reg["shapes"]
                      and np.abs(lm_deltas[j][groups[r]]).max() > 1e-6]
            if not moving:
                print("pupils: this rig cannot show gaze through its landmarks (its eyeLook* shapes, if any, do not "
                      "move the pupils: the eyeballs turn with bones), so the pupil keys stay at rest; gaze goes "
                      "to the eyeLook* curves and Live Link eye angles from the pupils with retarget --tracks")
                continue
        print(f"{r}: {len(reg['keys'])} keys onto {len(reg['shapes'])} rig shapes")
        for k, pose in reg["keys"].items():
            top = sorted(pose.items(), key=lambda kv: -kv[1])[:4]
            print(f"  {k}: " + (", ".join(f"{s} {v:.2f}" for s, v in top) or "(rest)")
                  + f"  [residual {100 * fit[k]:.0f}%]")
    print(f"wrote {Path(args.output)}")
    if args.edit:
        from keyshape.retarget.pose_edit import serve
        serve(args.output, load_rig(args.rig if len(args.rig) > 1 else args.rig[0], args.neutral),
              args.keys, args.port)
    return 0


def run_edit(args) -> int:
    from keyshape.retarget.pose_edit import serve
    from keyshape.retarget.rig import load_rig

    rig = load_rig(args.rig if len(args.rig) > 1 else args.rig[0], args.neutral)
    serve(args.poses, rig, args.keys, args.port)
    return 0
