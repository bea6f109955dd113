"""``keyshape pose``: suggest each key shape's pose on an artist's blendshape rig (a pose library)."""
from __future__ import annotations

import argparse

from keyshape.base import options


def add_rig_options(p) -> None:
    """``--rig``, ``--neutral`` and ``--landmarks``, as ``keyshape pose`` and ``keyshape solve`` take them."""
    p.add_argument("--rig", nargs="+", required=True, metavar="DIR|FILE",
                   help="rig: folder of shape OBJs (or a list of OBJ files) of one topology")
    p.add_argument("--neutral", default=None,
                   help="the rig's neutral OBJ (default: the folder's neutral.* or generic_neutral_mesh.obj)")
    p.add_argument("--landmarks", default=None,
                   help="rig landmarks: a keyshape-rig-landmarks JSON (the rig vertices of the scheme's points) or "
                        "the rig's iBUG-68 vertex list, a JSON list or one index a line (default: the shipped "
                        "correspondence for ICT-FaceKit rigs, else found on the rig and written beside the output, "
                        "OUT.landmarks.json)")


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
    add_rig_options(p)
    p.add_argument("-o", "--output", required=True, help="POSES.json to write")
    p.add_argument("--edit", action="store_true",
                   help="then serve a local page (127.0.0.1) to correct the poses by hand; Ctrl-C stops it")
    p.add_argument("--port", type=options.port, default=8766, help="port of the --edit page (0: any free port)")
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
    e.add_argument("--port", type=options.port, default=8766, help="port on 127.0.0.1 (0: any free port)")
    e.set_defaults(func=run_edit)


def describe_residual(residual: float) -> str:
    """A pose fit's relative residual in words: what it means and what to do about it."""
    if residual <= 0.25:
        return "good"
    if residual <= 0.5:
        return "fair: the rig shows this key's motion only in part; check it in 'keyshape pose-edit'"
    return ("poor: no mix of the region's rig shapes makes this key's motion (a shape the rig lacks, or a key "
            "spoiled by tracking or head motion); correct it by hand in 'keyshape pose-edit' or select keys again")


def run(args) -> int:
    import time
    from pathlib import Path

    from keyshape.base.formats.keys import read_keys, read_keys_head_pose, read_keys_source
    from keyshape.base.formats.poses import write_poses
    from keyshape.retarget.api import fit_poses
    from keyshape.retarget.rig.model import load_rig

    scheme_name, n_points, regions = read_keys(args.keys)
    t0 = time.perf_counter()
    print(f"keyshape pose: loading the rig {' '.join(map(str, args.rig))} ...", flush=True)
    rig = load_rig(args.rig, args.neutral, with_mesh=False)
    n_keys = sum(len(rk.keys) for rk in regions)
    print(f"keyshape pose: {rig.n_shapes} shapes of {rig.n_vertices} vertices ({time.perf_counter() - t0:.1f} s); "
          f"fitting {n_keys} keys of {len(regions)} regions ...", flush=True)
    from keyshape.retarget.rig.landmarks_cli import resolve_landmarks
    args.landmarks = resolve_landmarks(rig, scheme_name, args.landmarks, args.output)
    t1 = time.perf_counter()
    data, fit = fit_poses(regions, scheme_name, rig, read_keys_head_pose(args.keys), args.landmarks)
    data = {"keys": {"file": str(args.keys), "scheme": scheme_name}, **data}
    src = read_keys_source(args.keys)
    if src.get("model"):
        data["keys"]["model"] = src["model"]
    from keyshape.base.files import sha256_file
    data["keys"]["sha256"] = sha256_file(args.keys)          # which key set exactly (provenance)
    write_poses(args.output, data)
    print(f"keyshape pose: fitted in {time.perf_counter() - t1:.1f} s. Residual: the share of the key's landmark "
          "motion the pose does not reproduce (0% exact; above 50% the rig cannot make this key)")
    poor = []
    for r, reg in data["regions"].items():
        if r == "pupils" and (not reg["shapes"] or all(fit[k] > 0.999 for k in reg["keys"])):
            print("pupils: this rig cannot show gaze through its landmarks (no shape of it moves the pupils: "
                  "ICT-FaceKit turns its eyeballs with bones), so the pupil keys stay at rest; gaze goes to the "
                  "eyeLook* curves and the Live Link eye angles from the pupils (retarget/solve with --tracks)")
            continue
        print(f"{r}: {len(reg['keys'])} keys onto {len(reg['shapes'])} rig shapes")
        for k, pose in reg["keys"].items():
            top = sorted(pose.items(), key=lambda kv: -kv[1])[:4]
            print(f"  {k}: " + (", ".join(f"{s} {v:.2f}" for s, v in top) or "(rest)")
                  + f"  [residual {100 * fit[k]:.0f}%: {describe_residual(fit[k]).split(':')[0]}]")
            if fit[k] > 0.25:
                poor.append(k)
    if poor:
        worst = max(poor, key=lambda k: fit[k])
        print(f"keyshape pose: {len(poor)} key(s) with a high residual ({', '.join(poor)}); {worst}: "
              f"{describe_residual(fit[worst])}")
    print(f"wrote {Path(args.output)}")
    if args.edit:
        from keyshape.retarget.rig.pose_edit import serve
        serve(args.output, load_rig(args.rig, args.neutral), args.keys, args.port)
    return 0


def run_edit(args) -> int:
    from keyshape.retarget.rig.pose_edit import serve
    from keyshape.retarget.rig.model import load_rig

    from keyshape.base.errors import require_file
    require_file(args.poses, "pose library (POSES.json)")           # before the rig is loaded
    rig = load_rig(args.rig, args.neutral)
    serve(args.poses, rig, args.keys, args.port)
    return 0
