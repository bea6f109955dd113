"""``keyshape demo``: the whole video path on built-in synthetic footage, end to end.

1. ``keyshape synth video``: camcorder-like footage of a talking face with exact
   ground truth (landmarks, head pose, the hidden expression weights).
2. ``keyshape train`` on the 20 suggested labelled frames, then ``keyshape track``.
3. ``keyshape select`` (key shapes per region) and ``keyshape decompose`` (NNLS weights with
   a small ridge against tracking noise).
4. The artist's targets: for each key frame, the ICT-FaceKit expressions combined as
   the key frame shows them (known here from the hidden weights, as an artist
   would model a smiling target for a smiling key frame); then ``keyshape retarget``
   writes the ``.glb`` and a side-by-side preview video.

Because the synthetic performance is made of ICT-FaceKit-named components, the
ground-truth animation of the target face is known too: the demo reports the
tracking error (NME) and the retargeted face's vertex error against it.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from keyshape.decompose.cli import METHODS, SOLVERS
from keyshape.base.errors import KeyshapeError

# synthetic components -> demo region (contours48 regions used by decompose)
_REGION_OF = {"jaw": "mouth", "mouth": "mouth", "eye": "eyes", "brow": "eyes"}


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the whole video path on built-in synthetic footage")
    p.add_argument("out_dir", nargs="?", default="keyshape_demo", help="output folder (default: keyshape_demo)")
    p.add_argument("--frames", type=int, default=300, help="frames of synthetic footage (default 300)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic performance (default 0)")
    p.add_argument("--keys", type=int, default=8, help="key shapes per region (default 8)")
    p.add_argument("--method", default="greedy", choices=METHODS, help="key-shape selector (default greedy; spread is the paper's)")
    p.add_argument("--labels", type=int, default=20, help="labelled training frames (default 20)")
    p.add_argument("--solver", default="smooth", choices=SOLVERS,
                   help="weight solver for keyshape decompose (default smooth)")
    p.add_argument("--ridge", type=float, default=0.03,
                   help="keyshape decompose --ridge (default 0.03; 0 is the paper's plain NNLS)")
    p.set_defaults(func=run)


def _stage(argv: list[str]) -> None:
    from keyshape.cli import main

    print(f"$ keyshape {' '.join(argv)}", flush=True)
    rc = main(argv)
    if rc:
        raise KeyshapeError(f"stage 'keyshape {argv[0]}' failed with status {rc}")


def _expand(ex, coeffs: dict[str, float]) -> dict[str, float]:
    """Map synthetic component names onto the expression set: a name the set has only with
    ``_L``/``_R`` suffixes (``browInnerUp``) drives both sides."""
    from keyshape.retarget.targets import name_key

    have = {name_key(n) for n in ex.names}
    out: dict[str, float] = {}
    for k, v in coeffs.items():
        if name_key(k) in have:
            out[k] = out.get(k, 0.0) + v
        else:
            for side in ("_L", "_R"):
                out[k + side] = out.get(k + side, 0.0) + v
    return out


def _region_coeffs(names, w, region: str) -> dict[str, float]:
    return {n: float(c) for n, c in zip(names, w)
            if any(n.startswith(p) and r == region for p, r in _REGION_OF.items())}


def run(args) -> int:
    run_demo(args.out_dir, frames=args.frames, seed=args.seed, keys=args.keys, method=args.method,
             labels=args.labels, solver=args.solver, ridge=args.ridge)
    return 0


def run_demo(out_dir, frames: int = 300, seed: int = 0, keys: int = 8, method: str = "greedy", labels: int = 20,
             solver: str = "smooth", ridge: float = 0.03) -> dict:
    """Run the demo into ``out_dir``; print and return the measured figures (also written to
    ``demo_report.json``): ``nme_mean``, ``nme_worst``, ``failed_frames``, ``target_error_mm``
    (mean vertex error of the retargeted face against the hidden performance on the same
    face), ``target_motion_mm`` (mean vertex motion of that performance: a still face's error),
    ``seconds``."""
    from keyshape.base.formats.keys import read_keys
    from keyshape.base.files import atomic_write
    from keyshape.retarget.demo_targets import demo_regions, load_expressions, write_demo_targets
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.schemes import load_scheme

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    foot = out / "footage"
    video = foot / "video.mp4"
    _stage(["synth", "video", str(foot), "--frames", str(frames), "--seed", str(seed), "--labels", str(labels),
            "--preview", str(foot / "preview.png")])
    _stage(["train", str(video), "--labels", str(foot / "labels"), "-o", str(out / "model.npz")])
    _stage(["track", str(video), "--model", str(out / "model.npz"), "-o", str(out / "tracks.csv"), "--quiet"])
    _stage(["select", str(out / "tracks.csv"), "-k", str(keys), "--method", method,
            "--region", "mouth", "--region", "eyes", "-o", str(out / "keys.json"),
            "--sheet", str(out / "keys.png"), "--video", str(video)])
    _stage(["decompose", str(out / "tracks.csv"), "--keys", str(out / "keys.json"), "--solver", solver,
            "--ridge", str(ridge), "-o", str(out / "weights.csv")])

    # the artist's targets, one per key shape, from what each key frame shows
    truth = json.loads((foot / "truth.json").read_text())
    names, hidden = truth["components"], np.asarray(truth["weights"], dtype=np.float64)
    ex = load_expressions()
    _, _, regions = read_keys(out / "keys.json")
    # decompose's weights are relative to the mean shape, so a key's target is the mean face
    # with that region's expressions as the key frame shows them
    mean = dict(zip(names, hidden.mean(axis=0)))
    key_coeffs = {}
    for rk in regions:
        for name, frame in zip(rk.names, rk.frames):
            key_coeffs[name] = _expand(ex, {**mean, **_region_coeffs(names, hidden[int(frame)], rk.region)})
    neutral_coeffs = _expand(ex, mean)
    write_demo_targets(out / "targets", key_coeffs, ex, neutral_coeffs)
    regions_json = out / "targets_regions.json"
    regions_json.write_text(json.dumps({k: v.tolist() for k, v in demo_regions(ex).items()}))
    _stage(["retarget", str(out / "weights.csv"), "--targets", str(out / "targets"),
            "--regions", str(regions_json), "--tracks", str(out / "tracks.csv"), "-o", str(out / "animation.glb")])

    # side-by-side preview and measured errors against the ground truth
    report = _preview_and_errors(out, video, ex, names, hidden, key_coeffs, neutral_coeffs)
    scheme = load_scheme("contours48")
    tracks, gt = read_tracks(out / "tracks.csv"), read_tracks(foot / "truth.csv")
    nme = np.linalg.norm(tracks.points - gt.points, axis=-1).mean(axis=-1) / scheme.interocular_distance(gt.points)
    figures = {"nme_mean": float(np.nanmean(nme)), "nme_worst": float(np.nanmax(nme)),
               "failed_frames": int((~tracks.success).sum()), "target_error_mm": report["mean_mm"],
               "target_motion_mm": report["motion_mm"], "seconds": time.perf_counter() - t0}
    with atomic_write(out / "demo_report.json", "w") as f:
        json.dump(figures, f, indent=1)
    print(f"\nkeyshape demo: done in {figures['seconds']:.1f} s")
    print(f"  tracking NME vs ground truth: mean {figures['nme_mean']:.4f}, worst frame {figures['nme_worst']:.4f}; "
          f"{figures['failed_frames']} frames marked failed")
    print(f"  retargeted face vs ground-truth performance on the target: mean vertex error "
          f"{figures['target_error_mm']:.2f} mm (a still face's error, the performance's own motion: "
          f"{figures['target_motion_mm']:.2f} mm)")
    for label, path in [("footage", video), ("ground truth", foot / "truth.csv"), ("preview sheet", foot / "preview.png"),
                        ("tracker model", out / "model.npz"), ("tracks", out / "tracks.csv"),
                        ("key shapes", out / "keys.json"), ("key sheet", out / "keys.png"),
                        ("weights", out / "weights.csv"), ("targets", out / "targets"),
                        ("animation", out / "animation.glb"), ("preview video", out / "preview.mp4"),
                        ("figures", out / "demo_report.json")]:
        print(f"  {label:14s} {path}")
    return figures


def _preview_and_errors(out: Path, video: Path, ex, names, hidden, key_coeffs, neutral_coeffs) -> dict:
    """Write ``preview.mp4`` (source frame with tracked contours | rendered target face) and measure
    the retargeted face against the hidden performance applied to the same target face."""
    import cv2

    from keyshape.retarget.demo_targets import demo_regions, demo_targets
    from keyshape.retarget.render import render_frames, side_by_side
    from keyshape.retarget.retargeter import Retargeter
    from keyshape.base.formats.weights import read_weights
    from keyshape.base.draw import draw_shape
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.schemes import load_scheme
    from keyshape.base.formats.video import VideoReader, video_writer

    ts = demo_targets(key_coeffs, ex, neutral_coeffs)
    _, columns, weights = read_weights(out / "weights.csv")
    order = [columns.index(c) for c in ts.columns]
    frames = Retargeter(band=1.5).fit(ts, demo_regions(ex)).transform(weights[:, order])
    truth_frames = ex.shapes([_expand(ex, dict(zip(names, w))) for w in hidden])
    err = np.linalg.norm(frames - truth_frames, axis=-1) * 10.0  # cm -> mm
    motion = np.linalg.norm(truth_frames - ex.shape(neutral_coeffs), axis=-1) * 10.0
    scheme = load_scheme("contours48")
    tracks = read_tracks(out / "tracks.csv")
    reader = VideoReader(video)
    h = 360
    w_left = int(round(reader.info.width * h / reader.info.height))
    renders = render_frames(frames, ex.triangles, size=(h, h))
    with video_writer(out / "preview.mp4", reader.info.fps, (w_left + 4 + h, h)) as writer:
        for (i, frame), face in zip(reader, renders):
            left = cv2.resize(draw_shape(frame, tracks.points[i], scheme), (w_left, h), interpolation=cv2.INTER_AREA)
            writer.write(side_by_side(left, face))
    return {"mean_mm": float(err.mean()), "motion_mm": float(motion.mean())}
