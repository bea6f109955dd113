"""``keyshape animate``: footage to a rig in one command.

``keyshape animate take.mp4 --rig rig/ -o take.glb`` runs the video path's steps with their defaults, each
through :mod:`keyshape.api` as the step-by-step commands do, and hands each step's file to the next as
they do (so its curves are the chain's)::

    keyshape label take.mp4 --count 12 -o WORK/labels      (dlib's pre-fill, uncorrected; or --labels DIR)
    keyshape train take.mp4 --labels LABELS -o WORK/model.npz
    keyshape track take.mp4 --model WORK/model.npz -o WORK/tracks.csv
    keyshape select WORK/tracks.csv -k 8 --region mouth --region eyes -o WORK/keys.json
    keyshape solve WORK/tracks.csv --keys WORK/keys.json --rig rig/ -o take.glb     (each output)
    keyshape preview take.mp4 --tracks WORK/tracks.csv --curves ... --rig rig/ -o take_preview.mp4

The work folder (``--work``, default ``VIDEO-STEM_work`` beside the first output) keeps the labels, the
model, the tracks and the key set, and ``animate.json``, the record of what each was computed from
(content hashes, as ``keyshape batch`` keeps them with :func:`keyshape.batch.digest`): a rerun redoes a
step only where its inputs changed (corrected labels retrain; the same take and labels skip to the
outputs, and outputs whose inputs are unchanged are kept).

``keyshape animate --example OUT_DIR`` runs it on the short real clip shipped with the package
(:mod:`keyshape.data`, with its labels) onto a rig made from the shipped ICT-FaceKit face subset.
"""
from __future__ import annotations

import importlib.util
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from keyshape.base.errors import InputError

#: the record of a work folder (beside the files it describes)
RECORD = "animate.json"
RECORD_FORMAT = "keyshape-animate"
#: ``keyshape label``'s defaults: frames labelled, scheme, seed of the frame choice
LABEL_COUNT = 12
LABEL_SCHEME = "contours48"
LABEL_SEED = 0
#: README's key set: ``keyshape select -k 8 --region mouth --region eyes``
KEYS_PER_REGION = 8
REGIONS = ("mouth", "eyes")
#: what ``-o`` may write (the preview and Live Link have their own options)
OUTPUT_KINDS = ("glb", "usd", "csv")
STEPS = ("label", "train", "track", "select", "solve", "write")

DATA = Path(__file__).parent / "data"
EXAMPLE_CLIP = DATA / "cap12_clip.mp4"
EXAMPLE_LABELS = DATA / "cap12_clip_labels"


@dataclass
class AnimateResult:
    """What :func:`animate` did.

    Attributes
    ----------
    work : the work folder
    frames, lost : the take's tracked frames, and those the tracker lost
    keys : per region ``(region, frames of its keys)``
    calibration : the solve's lines on the eyes' and brows' calibration (as ``keyshape solve`` prints)
    outputs : per output ``(path, "written" | "unchanged")``
    steps : per step ``"done"``, ``"unchanged"`` or ``"given"``
    seconds : wall time
    """

    work: Path
    frames: int = 0
    lost: int = 0
    keys: list = field(default_factory=list)
    calibration: list = field(default_factory=list)
    outputs: list = field(default_factory=list)
    steps: dict = field(default_factory=dict)
    seconds: float = 0.0


def _say_to_stderr(line: str) -> None:
    import sys

    print(line, file=sys.stderr, flush=True)


def default_work(video: str | Path, first_output: str | Path) -> Path:
    """``VIDEO-STEM_work`` beside the first output."""
    return Path(first_output).parent / f"{Path(video).stem}_work"


def default_preview(first_output: str | Path) -> Path:
    """``OUTPUT-STEM_preview.mp4`` beside the first output."""
    p = Path(first_output)
    return p.with_name(f"{p.stem}_preview.mp4")


def _check_dlib() -> None:
    if importlib.util.find_spec("dlib") is None or importlib.util.find_spec("face_recognition_models") is None:
        raise InputError('no labels: give --labels DIR (from keyshape label), or install the dlib pre-fill: '
                         'pip install "keyshape[label]"')


def _check_work(work: Path) -> dict:
    """The work folder's record (empty for a new folder); refuse a folder that keyshape animate did not make
    (after :func:`~keyshape.base.files.check_outputs` has checked it as a folder output)."""
    from keyshape.batch import read_record

    if not work.is_dir() or not any(work.iterdir()):
        return {}
    rec = read_record(work / RECORD)
    if rec.get("format") != RECORD_FORMAT:
        raise InputError(f"folder is not empty and was not made by keyshape animate (no {RECORD}); choose "
                         "another --work", work)
    return rec


def animate(video: str | Path, rig, outputs: Sequence[str | Path] = (), *, livelink: str | Path | None = None,
            preview: str | Path | None = None, labels: str | Path | None = None, work: str | Path | None = None,
            landmarks: str | Path | None = None, say: Callable[[str], None] = _say_to_stderr) -> AnimateResult:
    """Drive ``rig`` from the take ``video`` in one call (``keyshape animate``); see the module docstring.

    Parameters
    ----------
    video : the take
    rig : the rig's folder (a neutral OBJ plus one OBJ per shape, as ``keyshape solve --rig``)
    outputs : .glb, .usda/.usdc/.usd (``keyshape[usd]``) or .csv (the rig's curves) files to write
    livelink : a Live Link Face CSV to write
    preview : the side-by-side preview video (default ``OUTPUT-STEM_preview.mp4`` beside the first output)
    labels : a label folder (``keyshape label``); None labels ``LABEL_COUNT`` frames with dlib's pre-fill
        (``keyshape[label]``), uncorrected, into the work folder
    work : the work folder (default ``VIDEO-STEM_work`` beside the first output)
    landmarks : the rig's landmark JSON (default: the shipped one for ICT-FaceKit rigs)
    say : where each step's progress line goes

    Returns
    -------
    :class:`AnimateResult`
    """
    from keyshape import __version__, api
    from keyshape.base.errors import require_file
    from keyshape.base.files import check_outputs
    from keyshape.base.formats.tracks import read_tracks, write_tracks
    from keyshape.batch import digest, file_sha, tree_sha, write_record
    from keyshape.retarget.output.export import output_kind
    from keyshape.retarget.rig.solve_cli import calibration_lines
    from keyshape.retarget.defaults import SolveOptions

    t0 = time.perf_counter()
    video = require_file(video, "video")
    outputs = [Path(o) for o in outputs]
    if not outputs and livelink is None:
        raise InputError("nothing to write: give -o OUT.glb (or .usd, .csv) and/or --livelink OUT.csv")
    for o in outputs:
        kind = output_kind(o, 3)
        if kind not in OUTPUT_KINDS:
            raise InputError("-o writes .glb, .usda/.usdc/.usd or .csv (the preview video is --preview)", o)
        if kind == "usd" and importlib.util.find_spec("pxr") is None:
            raise InputError('USD output needs usd-core: pip install "keyshape[usd]"', o)
    if livelink is not None and Path(livelink).suffix.lower() != ".csv":
        raise InputError("--livelink writes a .csv", livelink)
    first = outputs[0] if outputs else Path(livelink)
    preview = Path(preview) if preview is not None else default_preview(first)
    if preview.suffix.lower() not in (".mp4", ".avi"):
        raise InputError("--preview writes a .mp4 or .avi", preview)
    rig = Path(rig)
    if not rig.is_dir():
        raise InputError("--rig: expected the rig's folder (a neutral OBJ and one OBJ per shape)", rig)
    if landmarks is not None:
        require_file(landmarks, "rig landmarks")
    if labels is not None and not Path(labels).is_dir():
        raise InputError("--labels: expected a folder of NNNNNN.pts files (keyshape label)", labels)
    work = Path(work) if work is not None else default_work(video, first)
    inputs = [video, labels, rig, landmarks]
    check_outputs([*outputs, livelink, preview], [work], inputs)
    rec = _check_work(work)
    label_dir = Path(labels) if labels is not None else work / "labels"
    video_rec = file_sha(video, rec.get("video"))
    if labels is None:
        made_for = rec.get("labels_video_sha256")
        if made_for is not None and made_for != video_rec["sha256"] and label_dir.is_dir():
            raise InputError("holds labels of another video (this work folder was made for another take): choose "
                             "another --work, or give --labels", label_dir)
        if made_for is None:
            _check_dlib()
    res = AnimateResult(work)
    n = len(STEPS)

    def step(i: int, name: str, status: str, text: str) -> None:
        res.steps[name] = status
        say(f"keyshape animate: [{i}/{n}] {name}: {text}")

    def save() -> None:
        write_record(work / RECORD, rec)

    work.mkdir(parents=True, exist_ok=True)
    rec.update(format=RECORD_FORMAT, video=video_rec)
    save()

    # 1. labels
    if labels is not None:
        step(1, "label", "given", f"{label_dir}")
    elif rec.get("labels_video_sha256") == video_rec["sha256"] and (label_dir / "session.json").is_file():
        step(1, "label", "unchanged", f"reusing {label_dir} (correct them: keyshape label {video} -o {label_dir} "
                                      "--serve)")
    else:
        from keyshape.tracker.labelling.prepare import prepare_label_folder

        s = time.perf_counter()
        session = prepare_label_folder(video, label_dir, LABEL_COUNT, LABEL_SCHEME, rng=LABEL_SEED, quiet=True)
        rec["labels_video_sha256"] = video_rec["sha256"]
        save()
        step(1, "label", "done", f"{len(session['frames'])} frames pre-filled with dlib, uncorrected -> {label_dir} "
                                 f"({time.perf_counter() - s:.1f} s)")

    # 2. train
    model_path = work / "model.npz"
    key = digest(["train", video_rec["sha256"], tree_sha(label_dir), __version__])
    if rec.get("model_key") == key and model_path.is_file() and file_sha(model_path)["sha256"] == rec.get("model_sha256"):
        step(2, "train", "unchanged", f"reusing {model_path}")
    else:
        s = time.perf_counter()
        model = api.train(video, label_dir)
        model.save(model_path)
        rec.update(model_key=key, model_sha256=file_sha(model_path)["sha256"])
        save()
        step(2, "train", "done", f"{len(model.train_poses_)} labelled frames, {model.k_} components -> {model_path} "
                                 f"({time.perf_counter() - s:.1f} s)")

    # 3. track
    tracks_path = work / "tracks.csv"
    key = digest(["track", video_rec["sha256"], rec["model_sha256"], __version__])
    if rec.get("track_key") == key and tracks_path.is_file() and \
            file_sha(tracks_path)["sha256"] == rec.get("tracks_sha256"):
        tracks = read_tracks(tracks_path)
        step(3, "track", "unchanged", f"reusing {tracks_path}")
    else:
        s = time.perf_counter()
        tracks = api.track(video, model_path, jobs=None, progress=True)     # keyshape track's defaults
        write_tracks(tracks_path, tracks)
        rec.update(track_key=key, tracks_sha256=file_sha(tracks_path)["sha256"])
        save()
        tracks = read_tracks(tracks_path)                                   # what the later steps read
        step(3, "track", "done", f"{tracks.n_frames} frames, {int((~tracks.success).sum())} lost -> {tracks_path} "
                                 f"({time.perf_counter() - s:.1f} s)")
    res.frames, res.lost = int(tracks.n_frames), int((~tracks.success).sum())

    # 4. select
    keys_path = work / "keys.json"
    key = digest(["select", rec["tracks_sha256"], KEYS_PER_REGION, list(REGIONS), __version__])
    if rec.get("keys_key") == key and keys_path.is_file() and file_sha(keys_path)["sha256"] == rec.get("keys_sha256"):
        status, text = "unchanged", f", reusing {keys_path}"
    else:
        api.select(tracks, KEYS_PER_REGION, regions=list(REGIONS)).save(keys_path)
        rec.update(keys_key=key, keys_sha256=file_sha(keys_path)["sha256"])
        save()
        status, text = "done", f" -> {keys_path}"
    keys = api.Keys.load(keys_path)
    res.keys = [(rk.region, [int(f) for f in rk.frames]) for rk in keys.regions]
    step(4, "select", status, "; ".join(f"{r} {len(f)} keys" for r, f in res.keys) + text)

    # 5. solve, 6. write: an output is kept where it is the one these inputs gave
    base = [rec["tracks_sha256"], rec["keys_sha256"], tree_sha(rig), tree_sha(landmarks), __version__]
    wanted = [(p, output_kind(p, 3)) for p in outputs] + [(preview, "preview")]
    if livelink is not None:
        wanted.insert(len(outputs), (Path(livelink), "livelink"))
    done = rec.setdefault("outputs", {})
    todo = []
    for p, kind in wanted:
        okey = digest(["output", kind, *base, video_rec["sha256"] if kind == "preview" else None])
        old = done.get(str(Path(p).resolve()), {})
        same = old.get("key") == okey and Path(p).is_file() and file_sha(Path(p))["sha256"] == old.get("sha256")
        (res.outputs.append((Path(p), "unchanged")) if same else todo.append((Path(p), kind, okey)))
    if todo:
        s = time.perf_counter()
        r = api.load_rig(rig)
        anim = api.solve(tracks, keys, r, SolveOptions(landmarks=None if landmarks is None else str(landmarks)))
        res.calibration = calibration_lines(anim.calibration or {})
        rec["calibration"] = res.calibration
        step(5, "solve", "done", f"{len(anim.curves)} frames x {r.n_shapes} rig shapes at {anim.fps:g} fps "
                                 f"({time.perf_counter() - s:.1f} s)")
        s = time.perf_counter()
        for p, kind, okey in todo:
            if kind == "preview":
                api.preview(video, tracks, anim, p)
            else:
                anim.export(p, livelink=(kind == "livelink"))
            done[str(p.resolve())] = {"key": okey, "sha256": file_sha(p)["sha256"]}
            save()
            res.outputs.append((p, "written"))
        step(6, "write", "done", ", ".join(str(p) for p, _, _ in todo) + f" ({time.perf_counter() - s:.1f} s)")
    else:
        res.calibration = list(rec.get("calibration", []))
        step(5, "solve", "unchanged", "every output is the one these inputs give")
        step(6, "write", "unchanged", "every output unchanged")
    save()
    res.seconds = time.perf_counter() - t0
    return res


def summary(res: AnimateResult) -> list[str]:
    """The short summary ``keyshape animate`` prints at the end."""
    lines = [f"keyshape animate: {res.frames} frames ({res.lost} lost) in {res.seconds:.1f} s; work folder {res.work}",
             "  keys: " + "; ".join(f"{r} at frames {', '.join(map(str, f))}" for r, f in res.keys)]
    lines += [f"  {c}" for c in res.calibration]
    lines += [f"  {st}: {p}" for p, st in res.outputs]
    return lines


# ---------------------------------------------------------------- the example

def example(out_dir: str | Path, say: Callable[[str], None] = _say_to_stderr) -> AnimateResult:
    """:func:`animate` on the shipped clip and its labels onto a rig from the shipped ICT-FaceKit subset:
    ``OUT_DIR/animation.glb``, ``curves.csv`` and ``preview.mp4`` (the rig and the work in ``OUT_DIR/work``)."""
    from keyshape.data_synth.library import ict_subset_rig

    out = Path(out_dir)
    work = out / "work"
    files = [out / "animation.glb", out / "curves.csv"]
    preview = out / "preview.mp4"
    from keyshape.base.files import check_outputs

    check_outputs([*files, preview], [work])
    _check_work(work)
    rig, lm = work / "rig", work / "rig_landmarks.json"
    if not (rig / "neutral.obj").is_file() or not lm.is_file():
        from keyshape.batch import read_record, write_record

        work.mkdir(parents=True, exist_ok=True)
        write_record(work / RECORD, {**read_record(work / RECORD), "format": RECORD_FORMAT})
        ict_subset_rig(rig)
    say(f"$ keyshape animate {EXAMPLE_CLIP} --labels {EXAMPLE_LABELS} --rig {rig} --landmarks {lm} "
        f"-o {files[0]} -o {files[1]} --preview {preview} --work {work}")
    return animate(EXAMPLE_CLIP, rig, files, preview=preview, labels=EXAMPLE_LABELS, work=work, landmarks=lm,
                   say=say)


# ---------------------------------------------------------------- the command

def register(subparsers) -> None:
    """Add ``keyshape animate`` to ``subparsers``."""
    p = subparsers.add_parser(
        "animate", help="footage to a rig in one command: label, train, track, select, solve, outputs, preview",
        usage="keyshape animate VIDEO --rig DIR -o OUT [-o OUT ...] [--livelink OUT.csv] [--preview OUT.mp4] "
              "[--labels DIR] [--landmarks JSON] [--work DIR] | keyshape animate --example OUT_DIR",
        description="Run the video path on one take with the step-by-step commands' defaults (label 12 frames "
                    "with dlib's pre-fill unless --labels, train, track, select -k 8 --region mouth --region eyes, "
                    "solve) and write the rig's curves to each -o, the Live Link CSV and the side-by-side preview. "
                    "The work folder keeps each step's file and a record of what it came from: a rerun redoes "
                    "only what changed. --example OUT_DIR runs it on the clip shipped with keyshape.")
    p.add_argument("video", nargs="?", help="the take")
    p.add_argument("--rig", metavar="DIR", help="the rig: a neutral OBJ and one OBJ per shape, one topology")
    p.add_argument("-o", "--output", action="append", default=None, metavar="OUT",
                   help="OUT.glb, OUT.usda/.usdc/.usd or OUT.csv (the rig's curves); repeat for several")
    p.add_argument("--livelink", metavar="OUT.csv", help="also a Live Link Face CSV (ARKit names)")
    p.add_argument("--preview", metavar="OUT.mp4",
                   help="the footage beside the rig (default: the first output's name + _preview.mp4)")
    p.add_argument("--labels", metavar="DIR",
                   help="labelled frames (keyshape label); default: 12 frames pre-filled by dlib, uncorrected "
                        "(needs keyshape[label])")
    p.add_argument("--landmarks", metavar="JSON",
                   help="the rig's landmark JSON (default: the shipped one for ICT-FaceKit rigs)")
    p.add_argument("--work", metavar="DIR",
                   help="work folder, reused when the inputs are unchanged (default: VIDEO-STEM_work beside the "
                        "first output)")
    p.add_argument("--example", metavar="OUT_DIR",
                   help="run on the short real clip shipped with keyshape (with its labels) onto a rig from the "
                        "shipped ICT-FaceKit face: OUT_DIR/animation.glb, curves.csv, preview.mp4")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.example is not None:
        given = [f for f, v in (("VIDEO", args.video), ("--rig", args.rig), ("-o", args.output),
                                ("--livelink", args.livelink), ("--preview", args.preview), ("--labels", args.labels),
                                ("--landmarks", args.landmarks), ("--work", args.work)) if v]
        if given:
            raise InputError(f"--example runs on the shipped clip into OUT_DIR: not with {', '.join(given)}")
        res = example(args.example)
    else:
        if args.video is None or args.rig is None:
            raise InputError("give the take and the rig: keyshape animate VIDEO --rig DIR -o OUT.glb "
                             "(or --example OUT_DIR)")
        res = animate(args.video, args.rig, args.output or [], livelink=args.livelink, preview=args.preview,
                      labels=args.labels, work=args.work, landmarks=args.landmarks)
    print("\n".join(summary(res)))
    return 0
