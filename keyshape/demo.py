"""``keyshape demo``: the whole video path on built-in synthetic footage, end to end.

Design notes and figures: docs/tutorial.md, "Notes on the code", ``keyshape/demo.py``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from keyshape.base import options
from keyshape.decompose import defaults as D

# synthetic components -> demo region (contours48 regions used by decompose)
_REGION_OF = {"jaw": "mouth", "mouth": "mouth", "eye": "eyes", "brow": "eyes"}


#: ``keyshape demo``'s key shapes per region and labelled training frames (``run_demo(keys=..., labels=...)``
#: for others)
KEYS = 8
LABELS = 20


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the whole video path on built-in synthetic footage")
    p.add_argument("out_dir", nargs="?", default="keyshape_demo", help="output folder (default: keyshape_demo)")
    p.add_argument("--frames", type=options.synth_frames, default=300, help="frames of synthetic footage (default 300)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder keyshape did not make (only its own files are replaced)")
    p.set_defaults(func=run)


def _step(text: str) -> None:
    print(f"$ {text}", flush=True)


def _expand(ex, coeffs: dict[str, float]) -> dict[str, float]:
    """Map synthetic component names onto the expression set: a name the set has only with
    ``_L``/``_R`` suffixes (``browInnerUp``) drives both sides."""
    from keyshape.retarget.targets.target_set import name_key

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
    run_demo(args.out_dir, frames=args.frames, keys=KEYS, labels=LABELS, overwrite=args.overwrite)
    return 0


def run_demo(out_dir, frames: int = 300, seed: int = 0, keys: int = 8, method: str = D.METHOD, labels: int = 20,
             solver: str = D.SOLVER, ridge: float = D.RIDGE, overwrite: bool = False) -> dict:
    """Run the demo into ``out_dir`` (see :func:`_run_demo`). Every stage works in a hidden
    temporary folder inside ``out_dir``; the results replace an earlier demo's only when the
    whole demo has finished, so an interrupted or failed demo leaves ``out_dir`` as it was, and
    files keyshape did not write there are never touched."""
    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_dir

    if frames < 2 or keys < 1 or labels < 2:
        raise InputError(f"demo: frames {frames} and labels {labels} must be >= 2, keys {keys} >= 1")
    with atomic_dir(out_dir, overwrite, kind="demo") as tmp:
        figures = _run_demo(tmp, frames, seed, keys, method, labels, solver, ridge, final=Path(out_dir))
    _print_summary(Path(out_dir), figures)
    return figures


def _run_demo(out: Path, frames: int, seed: int, keys: int, method: str, labels: int,
              solver: str, ridge: float, final: Path | None = None) -> dict:
    """Run the demo into the folder ``out`` (printing each step with the paths its files will have in
    ``final``, where ``out`` is moved once the demo is done); return the measured figures (also written to
    ``demo_report.json``): ``nme_mean``, ``nme_worst``, ``failed_frames``, ``target_error_mm``
    (mean vertex error of the retargeted face against the hidden performance on the same
    face), ``target_motion_mm`` (mean vertex motion of that performance: a still face's error),
    ``seconds``."""
    from keyshape import api
    from keyshape.base.files import write_json
    from keyshape.base.formats.tracks import read_tracks, write_tracks
    from keyshape.data_synth.video import synthesize
    from keyshape.decompose.cli import write_sheet
    from keyshape.decompose.regions import stable_pose
    from keyshape.base.schemes import load_scheme
    from keyshape.retarget.targets.demo import demo_regions, load_expressions, write_demo_targets

    def at(p) -> Path:
        """Where ``p`` (inside ``out``) will be once the demo is done."""
        return Path(p) if final is None else Path(final) / Path(p).relative_to(out)

    t0 = time.perf_counter()
    foot = out / "footage"
    video = foot / "video.mp4"
    _step(f"synthesize({str(at(foot))!r}, frames={frames}, seed={seed}, labels={labels})")
    synthesize(foot, frames=frames, seed=seed, labels=labels, preview=foot / "preview.png")
    print(f"  {frames} frames and ground truth -> {at(foot)}")
    _step(f"model = train({str(at(video))!r}, {str(at(foot / 'labels'))!r})")
    model = api.train(video, foot / "labels")
    model.save(out / "model.npz")
    print(f"  {len(model.train_poses_)} labelled frames + {model.n_samples_ - len(model.train_poses_)} morphs, "
          f"{model.k_} components -> {at(out / 'model.npz')}")
    _step("tracks = track(video, model)")
    tracks = api.track(video, model)
    write_tracks(out / "tracks.csv", tracks)
    print(f"  {tracks.n_frames} frames, {int((~tracks.success).sum())} lost -> {at(out / 'tracks.csv')}")
    _step(f"keys = select(tracks, k={keys}, method={method!r}, regions=['mouth', 'eyes'])")
    key_set = api.select(tracks, keys, method, ["mouth", "eyes"])
    key_set.save(out / "keys.json")
    print(f"  -> {at(out / 'keys.json')}, key sheet {at(out / 'keys.png')}")
    write_sheet(out / "keys.png", video, tracks, load_scheme(key_set.scheme), key_set.regions,
                stable_pose(tracks, key_set.head_pose))
    for rk in key_set.regions:
        print(f"  {rk.region}: {len(rk.keys)} keys ({rk.method}) at frames {', '.join(map(str, rk.frames))}")
    _step(f"weights = decompose(tracks, keys, solver={solver!r}, ridge={ridge})")
    weights = api.decompose(tracks, key_set, solver, ridge)
    weights.save(out / "weights.csv")
    print(f"  {len(weights.frames)} frames x {len(weights.names)} weights -> {at(out / 'weights.csv')}")

    # the artist's targets, one per key shape, from what each key frame shows
    truth = json.loads((foot / "truth.json").read_text())
    names, hidden = truth["components"], np.asarray(truth["weights"], dtype=np.float64)
    ex = load_expressions()
    # the weights are relative to the actor's neutral (the most relaxed frame, select's default), or to
    # the take's mean with --neutral-frame mean: a key's target is that face with the key's region's
    # expressions as the key frame shows them
    rest = key_set.regions[0].rest_frame
    base = dict(zip(names, hidden[int(rest)] if rest is not None and all(
        rk.rest is not None and np.allclose(rk.neutral, rk.rest) for rk in key_set.regions)
        else hidden.mean(axis=0)))
    key_coeffs = {}
    for rk in key_set.regions:
        for name, frame in zip(rk.names, rk.frames):
            key_coeffs[name] = _expand(ex, {**base, **_region_coeffs(names, hidden[int(frame)], rk.region)})
    neutral_coeffs = _expand(ex, base)
    write_demo_targets(out / "targets", key_coeffs, ex, neutral_coeffs)
    regions_json = out / "targets_regions.json"
    write_json(regions_json, {k: v.tolist() for k, v in demo_regions(ex).items()}, indent=None)
    _step(f"retarget(weights, {str(at(out / 'targets'))!r}, regions={str(at(regions_json))!r}, tracks=tracks)"
          f".export({str(at(out / 'animation.glb'))!r})")
    anim = api.retarget(weights, out / "targets", regions_json, tracks=tracks)
    info = anim.export(out / "animation.glb")
    print(f"  {len(weights.frames)} frames x {len(weights.names)} key shapes ({anim.retargeter.form_} form) at "
          f"{anim.fps:g} fps -> {at(info['path'])}")

    # side-by-side preview and measured errors against the ground truth
    report = _preview_and_errors(out, video, tracks, weights, ex, names, hidden, key_coeffs, neutral_coeffs)
    scheme = load_scheme("contours48")
    gt = read_tracks(foot / "truth.csv")
    nme = np.linalg.norm(tracks.points - gt.points, axis=-1).mean(axis=-1) / scheme.interocular_distance(gt.points)
    figures = {"nme_mean": float(np.nanmean(nme)), "nme_worst": float(np.nanmax(nme)),
               "failed_frames": int((~tracks.success).sum()), "target_error_mm": report["mean_mm"],
               "target_motion_mm": report["motion_mm"], "seconds": time.perf_counter() - t0}
    write_json(out / "demo_report.json", figures)
    return figures


def _print_summary(out: Path, figures: dict) -> None:
    foot = out / "footage"
    video = foot / "video.mp4"
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


def _preview_and_errors(out: Path, video: Path, tracks, weights, ex, names, hidden, key_coeffs,
                        neutral_coeffs) -> dict:
    """Write ``preview.mp4`` (source frame with tracked contours | rendered target face) and measure
    the retargeted face against the hidden performance applied to the same target face."""
    import cv2

    from keyshape.retarget.targets.demo import demo_regions, demo_targets
    from keyshape.retarget.output.render import render_frames, side_by_side
    from keyshape.retarget.targets.retargeter import Retargeter
    from keyshape.base.draw import draw_shape
    from keyshape.base.schemes import load_scheme
    from keyshape.base.formats.video import VideoReader, video_writer

    ts = demo_targets(key_coeffs, ex, neutral_coeffs)
    order = [weights.names.index(c) for c in ts.columns]
    frames = Retargeter(band=1.5).fit(ts, demo_regions(ex)).transform(weights.values[:, order])
    truth_frames = ex.shapes([_expand(ex, dict(zip(names, w))) for w in hidden])
    err = np.linalg.norm(frames - truth_frames, axis=-1) * 10.0  # cm -> mm
    motion = np.linalg.norm(truth_frames - ex.shape(neutral_coeffs), axis=-1) * 10.0
    scheme = load_scheme("contours48")
    reader = VideoReader(video)
    h = 360
    w_left = int(round(reader.info.width * h / reader.info.height))
    renders = render_frames(frames, ex.triangles, size=(h, h))
    with video_writer(out / "preview.mp4", reader.info.fps, (w_left + 4 + h, h)) as writer:
        for (i, frame), face in zip(reader, renders):
            left = cv2.resize(draw_shape(frame, tracks.points[i], scheme), (w_left, h), interpolation=cv2.INTER_AREA)
            writer.write(side_by_side(left, face))
    return {"mean_mm": float(err.mean()), "motion_mm": float(motion.mean())}
