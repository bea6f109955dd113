"""``keyshape batch MANIFEST -o OUT_DIR``: a footage library through the video path on Dask distributed.

Design notes and figures: docs/batch.md, "Notes on the code", ``keyshape/batch.py``.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from keyshape import __version__
from keyshape.base.errors import InputError, KeyshapeError
from keyshape.base.files import InputSet, sha256_file, write_json
from keyshape.manifest import OUTPUT_FILES, Actor, Manifest, Settings, Take, read_manifest

REPORT_FORMAT = "keyshape-batch-report"

RECORD = "batch.json"
def _partial_pattern(token: str) -> re.Pattern:
    """Names of the hidden temporaries this run made (``.NAME.<token>-XXXX.partial[.SUFFIX]``)."""
    return re.compile(r"^\..+\." + re.escape(token) + r"-[A-Za-z0-9_]+\.partial(\.[A-Za-z0-9]+)?$")


# ---------------------------------------------------------------- hashing and records

def digest(obj) -> str:
    """sha256 of a JSON-able value (sorted keys)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def file_sha(path: Path, known: dict | None = None) -> dict:
    """``{path, size, mtime_ns, sha256}`` of a file; ``known`` (an earlier result) is reused when
    the size and modification time are unchanged, so an untouched video is not read again."""
    st = Path(path).stat()
    if known and known.get("size") == st.st_size and known.get("mtime_ns") == st.st_mtime_ns \
            and known.get("path") == str(path):
        return known
    return {"path": str(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": sha256_file(path)}


def tree_sha(path: Path | None) -> str | None:
    """sha256 over a file, or over a folder's files (relative names and contents); None for None."""
    if path is None:
        return None
    path = Path(path)
    if path.is_file():
        return file_sha(path)["sha256"]
    if not path.is_dir():
        from keyshape.base.errors import MissingFileError
        raise MissingFileError(path)
    return digest([(str(p.relative_to(path)), file_sha(p)["sha256"])
                   for p in sorted(path.rglob("*")) if p.is_file() and not p.name.startswith(".")])


def read_record(path: Path) -> dict:
    try:
        rec = json.loads(Path(path).read_text())
        return rec if isinstance(rec, dict) else {}
    except (OSError, ValueError):
        return {}


def write_record(path: Path, rec: dict) -> None:
    write_json(path, rec, end="\n", sort_keys=True)


def _failure(exc: BaseException) -> dict:
    if isinstance(exc, KeyshapeError):
        msg = str(exc)
    elif isinstance(exc, OSError):      # a file that cannot be read or written: name it, say why
        from keyshape.base.files import describe_os_error
        msg = describe_os_error(exc)
    elif isinstance(exc, MemoryError):
        msg = "out of memory (fewer --workers, or shorter takes with 'frames')"
    else:   # a bug, not bad input: keep the place it happened
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        msg = f"{type(exc).__name__}: {exc} ({Path(tb.filename).name}:{tb.lineno})"
    return {"ok": False, "error": msg}


#: What pins a worker's libraries to one thread: OpenMP, OpenBLAS, MKL and FFmpeg's decoder (read by OpenCV
#: when it opens a video). The local cluster sets them before it spawns each worker (before numpy is imported);
#: every task sets them again for workers started elsewhere (``dask worker`` without a nanny).
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                  "OPENCV_FFMPEG_THREADS": "1"}

#: ``keyshape batch``'s local cluster workers: processes (threads of one process with False: for debugging, the
#: tracker's Python holds the GIL; ``run_batch(processes=False)`` in the API)
PROCESSES = True
#: True in the process that runs :func:`run_batch` (thread workers share it: leave its libraries be).
_CLIENT_PROCESS = False


def _one_thread() -> None:
    """A worker is one core: its libraries run their parallel loops on the calling thread.

    OpenCV's own pool is set to one thread; in a worker process (not the client's, where thread
    workers run) also the BLAS/OpenMP pools, through threadpoolctl (the environment variables only act
    before the libraries load), and FFmpeg's decoder threads for the videos opened from now on. The
    tracker's decode-ahead thread stays (a worker tracks on one thread and decodes on another; see
    docs/scale.md). Results do not depend on any of it.
    """
    import cv2

    cv2.setNumThreads(1)
    if _CLIENT_PROCESS:
        return
    os.environ.update(ONE_THREAD_ENV)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def _task(fn):
    """A batch task: runs with :func:`_one_thread` and adds ``span`` to its result: when and where it ran
    (``start``/``end`` epoch seconds, the worker's ``pid``) and the CPU seconds of the worker process and of
    the task's own thread (``cpu`` above ``thread_cpu`` is what the process's other threads did meanwhile:
    the decode-ahead thread, Dask's own). The report lists them; bench/bench_batch.py reads them. An exception
    is the task's failed result (reported per actor or take: the batch goes on)."""
    @functools.wraps(fn)
    def run(*args, **kwargs) -> dict:
        _one_thread()
        t0, c0, th0, p0 = time.time(), time.process_time(), time.thread_time(), time.perf_counter()
        try:
            res = fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001
            res = {**_failure(exc), "seconds": time.perf_counter() - p0}
        res["span"] = {"start": round(t0, 4), "end": round(time.time(), 4), "pid": os.getpid(),
                       "cpu": round(time.process_time() - c0, 4), "thread_cpu": round(time.thread_time() - th0, 4)}
        return res
    return run


def _max_rss_mb() -> float | None:
    """Peak resident memory of this worker process so far (MiB; None where unknown)."""
    try:
        import resource
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return round(kb / (1 << 20 if sys.platform == "darwin" else 1 << 10), 1)
    except (ImportError, OSError):
        return None


def actor_dir(out: Path, actor: str) -> Path:
    return Path(out) / actor


def take_dir(out: Path, take: Take) -> Path:
    return Path(out) / take.actor / take.name


# ---------------------------------------------------------------- the tasks (run on the workers)

@_task
def task_model(actor: Actor, out: str) -> dict:
    """Train the actor's model once (or take its model file); skip when the record matches."""
    t0, c0 = time.perf_counter(), time.process_time()
    adir = actor_dir(Path(out), actor.name)
    rec_path = adir / RECORD
    rec = read_record(rec_path)
    if actor.model is not None:
        sha = file_sha(actor.model, rec.get("model_file"))
        from keyshape.tracker.eigenpoints import AppearanceModel
        AppearanceModel.load(actor.model, actor.scheme)    # fail here, once, on a bad model file
        rec.update(model_file=sha, model_key=digest(["file", sha["sha256"], __version__]))
        write_record(rec_path, rec)
        return {"ok": True, "path": str(actor.model), "key": rec["model_key"], "status": "given",
                "seconds": time.perf_counter() - t0}
    video = file_sha(actor.video, rec.get("video"))
    settings = [actor.scheme, actor.components, actor.morphs, actor.seed]
    key = digest(["train", video["sha256"], tree_sha(actor.labels), settings, __version__])
    path = adir / "model.npz"
    if rec.get("model_key") == key and path.is_file() and \
            file_sha(path)["sha256"] == rec.get("model_sha256"):
        return {"ok": True, "path": str(path), "key": key, "status": "skipped", "seconds": 0.0}
    from keyshape import api
    model = api.train(actor.video, actor.labels, scheme=actor.scheme, components=actor.components,
                      morphs=actor.morphs, seed=actor.seed)
    model.save(path)
    rec.update(video=video, model_key=key, model_sha256=file_sha(path)["sha256"])
    write_record(rec_path, rec)
    return {"ok": True, "path": str(path), "key": key, "status": "trained", "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0}


@_task
def task_track(take: Take, actor: Actor, settings: Settings, model: dict, out: str) -> dict:
    """Track one take with its actor's model -> tracks.csv; skip when video, model and settings are unchanged."""
    t0, c0 = time.perf_counter(), time.process_time()
    if not model["ok"]:
        return {"ok": False, "error": f"actor {actor.name!r}: {model['error']}", "seconds": 0.0}
    tdir = take_dir(Path(out), take)
    rec_path = tdir / RECORD
    rec = read_record(rec_path)
    video = file_sha(take.video, rec.get("video"))
    key = digest(["track", video["sha256"], model["key"], settings.smooth, take.start, take.stop, __version__])
    path = tdir / OUTPUT_FILES["tracks"]
    if rec.get("track_key") == key and path.is_file() and file_sha(path)["sha256"] == rec.get("tracks_sha256"):
        return {"ok": True, "status": "skipped", "path": str(path), "sha256": rec["tracks_sha256"],
                "stats": rec["stats"], "seconds": 0.0}
    from keyshape import api
    from keyshape.base.formats.tracks import write_tracks
    from keyshape.tracker.eigenpoints import AppearanceModel

    m = AppearanceModel.load(model["path"], actor.scheme)
    # a worker process is one core: it decodes on its tracking thread (thread workers share
    # the client's process and keep the decode-ahead thread)
    tracks = api.track(take.video, m, smooth=settings.smooth, start=take.start, stop=take.stop,
                       decode_thread=_CLIENT_PROCESS)
    write_tracks(path, tracks)
    seconds = time.perf_counter() - t0
    stats = {"frames": int(tracks.n_frames), "lost_frames": int((~tracks.success).sum()),
             **_short_take(take, tracks.n_frames),
             "confidence": float(np.mean(tracks.confidence)), "track_seconds": round(seconds, 3),
             "track_cpu_seconds": round(time.process_time() - c0, 3),
             "worker_max_rss_mb": _max_rss_mb()}
    # a re-tracked take invalidates its later stages: keep only what still holds
    # (which output files batch wrote here stays recorded: they are still batch's to replace)
    rec = {"video": video, "track_key": key, "tracks_sha256": file_sha(path)["sha256"], "stats": stats,
           **{k: rec[k] for k in ("outputs", "outputs_sha256") if k in rec}}
    write_record(rec_path, rec)
    return {"ok": True, "status": "tracked", "path": str(path), "sha256": rec["tracks_sha256"], "stats": stats,
            "seconds": seconds}


def _short_take(take: Take, n_frames: int) -> dict:
    """``{"warning": ...}`` when the video ended before the frames its header announces (or the
    take's frame range), as ``keyshape track`` warns; else {}."""
    from keyshape.base.formats.video import video_info

    try:
        announced = video_info(take.video).n_frames
    except (KeyshapeError, OSError):
        return {}
    expected = (min(take.stop, announced) if take.stop is not None and announced else
                (take.stop if take.stop is not None else announced)) - take.start
    if announced and n_frames < expected:
        return {"warning": f"{take.video} ended after {n_frames} of the {expected} frames its header announces "
                           "(truncated or damaged file); tracks written for the frames decoded"}
    return {}


@_task
def task_keys(actor: Actor, takes: list[Take], tracked: list[dict], out: str) -> dict:
    """One key selection for the actor over all its successfully tracked takes (in manifest order)."""
    t0, c0 = time.perf_counter(), time.process_time()
    used = [(t, r) for t, r in zip(takes, tracked) if r["ok"]]
    if not used:
        return {"ok": False, "error": f"actor {actor.name!r}: no take was tracked", "seconds": 0.0}
    adir = actor_dir(Path(out), actor.name)
    rec_path = adir / RECORD
    rec = read_record(rec_path)
    key = digest(["keys", [(t.name, r["sha256"]) for t, r in used], actor.keys, actor.selector, actor.regions,
                  actor.seed, actor.scheme, __version__])
    path = adir / "keys.json"
    names = [t.name for t, _ in used]
    if rec.get("keys_key") == key and path.is_file() and file_sha(path)["sha256"] == rec.get("keys_sha256"):
        return {"ok": True, "status": "skipped", "path": str(path), "sha256": rec["keys_sha256"],
                "takes": names, "offsets": rec.get("keys_offsets"), "seconds": 0.0}
    from keyshape import api
    from keyshape.base.formats.tracks import read_tracks

    tracks = [read_tracks(r["path"]) for _, r in used]
    keys = api.select(tracks, actor.keys, actor.selector, actor.regions, scheme=actor.scheme, seed=actor.seed)
    keys.save(path)
    offsets = np.concatenate([[0], np.cumsum([t.n_frames for t in tracks])[:-1]]).tolist()
    rec.update(keys_key=key, keys_sha256=file_sha(path)["sha256"], keys_takes=names, keys_offsets=offsets)
    write_record(rec_path, rec)
    return {"ok": True, "status": "selected", "path": str(path), "sha256": rec["keys_sha256"], "takes": names,
            "offsets": offsets, "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0}


def _unchanged(files: dict, recorded: dict | None) -> bool:
    """Every file is there with the content hash recorded when it was written (a truncated
    weights.csv or an emptied .glb is redone, not reused)."""
    if not isinstance(recorded, dict):
        return False
    for o, p in files.items():
        p = Path(p)
        if not p.is_file() or recorded.get(o) != file_sha(p)["sha256"]:
            return False
    return True


def finish_take(tracks_path, keys_path, actor: Actor, settings: Settings, tdir: Path, outputs: list[str],
                poses_path=None, video=None) -> dict:
    """Decompose one take with the actor's key set and retarget it (onto its targets, or its rig: the rig's
    curves solved from the tracks, with the manifest's corrected pose library ``poses`` over them when it
    gives one); write the outputs; return their paths.

    The serial reference of the batch: exactly what the finish task runs, and what the commands
    (``keyshape decompose``, ``retarget``, ``solve``, ``preview``) give with the manifest's settings.
    """
    from keyshape import api
    from keyshape.base.formats.tracks import read_tracks

    tracks = read_tracks(tracks_path)
    keys = api.Keys.load(keys_path)
    weights = api.decompose(tracks, keys, settings.solver, settings.ridge, settings.smooth_lambda)
    files = {"tracks": str(tracks_path)}
    wpath = tdir / OUTPUT_FILES["weights"]
    weights.save(wpath)
    files["weights"] = str(wpath)
    wanted = [o for o in outputs if o not in ("tracks", "weights")]
    if not wanted:
        return files
    weights = api.Weights.load(wpath)
    if actor.rig is not None:
        given = actor.poses is not None                 # a pose library the artist corrected
        anim = api.solve(tracks, keys, actor.rig, api.SolveOptions(landmarks=actor.landmarks), neutral=actor.neutral,
                         poses=poses_path if given else None, weights=weights if given else None)
    elif actor.targets is not None:
        anim = api.retarget(weights, actor.targets, actor.target_regions, tracks=tracks, neutral=actor.neutral,
                            mapping=actor.map)
    else:
        return files
    for o in wanted:
        p = tdir / OUTPUT_FILES[o]
        if o == "preview" and actor.rig is not None:
            api.preview(video, tracks, anim, p)
        else:
            anim.export(p, livelink=(o == "livelink"))
        files[o] = str(p)
    return files


@_task
def task_poses(actor: Actor, keys: dict, out: str) -> dict:
    """The actor's pose library on its rig: the manifest's ``poses`` file, or ``keyshape pose``'s suggestion
    fitted once from the actor's key set -> ``OUT_DIR/<actor>/poses.json``; skip when keys and rig are unchanged."""
    t0 = time.perf_counter()
    if actor.rig is None:
        return {"ok": True, "path": None, "sha256": None, "status": "none", "seconds": 0.0}
    if not keys["ok"]:
        return {"ok": False, "error": keys["error"], "seconds": 0.0}
    if actor.poses is not None:
        from keyshape import api
        api.PoseLibrary.load(actor.poses, api.load_rig(actor.rig, actor.neutral, with_mesh=False))
        return {"ok": True, "path": str(actor.poses), "sha256": file_sha(actor.poses)["sha256"],
                "status": "given", "seconds": time.perf_counter() - t0}
    adir = actor_dir(Path(out), actor.name)
    rec_path = adir / RECORD
    rec = read_record(rec_path)
    key = digest(["poses", keys["sha256"], tree_sha(actor.rig), tree_sha(actor.neutral),
                  tree_sha(actor.landmarks), __version__])
    path = adir / "poses.json"
    now = file_sha(path)["sha256"] if path.is_file() else None
    if rec.get("poses_key") == key and now is not None and now == rec.get("poses_sha256"):
        return {"ok": True, "status": "skipped", "path": str(path), "sha256": rec["poses_sha256"],
                "seconds": 0.0}
    if now is not None and "poses_sha256" in rec and now != rec["poses_sha256"]:
        # the artist corrected it (pose-edit): the corrections are why the file exists
        if rec.get("poses_key") != key:
            raise InputError("was changed since keyshape batch wrote it (corrected in pose-edit?) and its key "
                             "set or rig has changed since: batch does not refit over your corrections. To "
                             "keep them, give the file as the actor's 'poses' in the manifest; to discard "
                             "them, delete it and rerun", path)
        from keyshape import api
        api.PoseLibrary.load(path, api.load_rig(actor.rig, actor.neutral, with_mesh=False))
        return {"ok": True, "status": "edited", "path": str(path), "sha256": now,
                "seconds": time.perf_counter() - t0}
    from keyshape import api
    lib = api.pose(api.Keys.load(keys["path"]), actor.rig, neutral=actor.neutral, landmarks=actor.landmarks)
    lib.data["keys"]["file"] = str(keys["path"])
    lib.save(path)
    rec = read_record(rec_path)
    rec.update(poses_key=key, poses_sha256=file_sha(path)["sha256"])
    write_record(rec_path, rec)
    return {"ok": True, "status": "fitted", "path": str(path), "sha256": rec["poses_sha256"],
            "seconds": time.perf_counter() - t0}


@_task
def task_finish(take: Take, actor: Actor, settings: Settings, tracked: dict, keys: dict, out: str,
                poses: dict | None = None) -> dict:
    """Decompose and retarget one take; skip when tracks, key set, targets (or rig and poses) and settings
    are unchanged."""
    t0, c0 = time.perf_counter(), time.process_time()
    base = {"actor": take.actor, "take": take.name, "video": str(take.video)}
    if not tracked["ok"]:
        return {**base, "ok": False, "error": tracked["error"], "seconds": tracked.get("seconds", 0.0)}
    stages = {"track": tracked["status"]}
    poses = poses or {"ok": True, "path": None, "sha256": None}
    for res in (keys, poses):
        if not res["ok"]:
            return {**base, "ok": False, "error": res["error"], "stats": tracked["stats"], "stages": stages,
                    "seconds": tracked["seconds"]}
    try:
        tdir = take_dir(Path(out), take)
        rec_path = tdir / RECORD
        rec = read_record(rec_path)
        driven = actor.targets is not None or actor.rig is not None
        outputs = settings.outputs if driven else ["tracks", "weights"]
        key = digest(["finish", tracked["sha256"], keys["sha256"], settings.solver, settings.ridge,
                      settings.smooth_lambda, outputs, [tree_sha(p) for p in (actor.targets, actor.neutral, actor.map,
                                                                              actor.target_regions, actor.rig,
                                                                              actor.landmarks)],
                      poses["sha256"], str(take.video) if "preview" in outputs else None, __version__])
        files = {o: str(tdir / OUTPUT_FILES[o]) for o in outputs}
        if rec.get("finish_key") == key and _unchanged(files, rec.get("outputs_sha256")):
            stages["finish"] = "skipped"
        else:
            files = finish_take(tracked["path"], keys["path"], actor, settings, tdir, outputs, poses["path"],
                                take.video)
            rec["finish_key"] = key
            rec["outputs"] = files
            rec["outputs_sha256"] = {o: file_sha(Path(p))["sha256"] for o, p in files.items()}
            write_record(rec_path, rec)
            stages["finish"] = "done"
        finish = time.perf_counter() - t0
        return {**base, "ok": True, "stats": tracked["stats"], "outputs": files, "stages": stages,
                "seconds": tracked["seconds"] + finish, "finish_seconds": finish,
                "finish_cpu_seconds": time.process_time() - c0}
    except Exception as exc:  # noqa: BLE001
        return {**base, **_failure(exc), "stats": tracked["stats"], "stages": stages,
                "seconds": tracked["seconds"] + time.perf_counter() - t0}


# ---------------------------------------------------------------- the driver

def remove_partials(out: Path, manifest: Manifest, token: str | None = None) -> int:
    """Remove the hidden temporary files this interrupted run left in the folders the batch writes; return how
    many. Only names carrying this run's token (:func:`keyshape.base.files.run_token`, shared with the workers
    through ``KEYSHAPE_RUN_TOKEN``) are removed: a user's file that merely looks like a temporary is kept."""
    from keyshape.base.files import run_token

    partial = _partial_pattern(token or run_token())
    n = 0
    dirs = {actor_dir(out, a) for a in manifest.actors} | {take_dir(out, t) for t in manifest.takes} | {Path(out)}
    for d in dirs:
        if d.is_dir():
            for p in d.iterdir():
                if partial.match(p.name) and p.is_file() and not p.is_symlink():
                    p.unlink(missing_ok=True)
                    n += 1
    return n


_SCHEDULER = re.compile(r"(tcp|tls|ucx|ws|wss|inproc)://[A-Za-z0-9_.\-\[\]:%]+/?")


def check_scheduler(scheduler: str | None) -> None:
    """Refuse a ``--scheduler`` that is not an address such as ``tcp://HOST:PORT``."""
    if scheduler is None:
        return
    if not _SCHEDULER.fullmatch(scheduler):
        raise InputError(f"--scheduler {scheduler!r}: expected an address such as tcp://HOST:PORT")
    port = scheduler.rstrip("/").rsplit(":", 1)[-1]
    if scheduler.count(":") >= 2 and port.isdigit() and not 0 < int(port) < 65536:
        raise InputError(f"--scheduler {scheduler!r}: port {port} is not in 1..65535")


_RECORD_KEYS = ("model_key", "model_file", "keys_key", "track_key", "finish_key")


def _batch_record(path: Path) -> dict | None:
    """The batch record at ``path`` when there is one keyshape batch wrote, else None."""
    rec = read_record(path)
    return rec if any(k in rec for k in _RECORD_KEYS) else None


def check_layout(m: Manifest, out: Path) -> None:
    """Before any work: refuse a run that would write over an input, into an input folder, or over a
    file that keyshape batch did not write there.

    A file is batch's when the record beside it (``batch.json``) says batch wrote it (then a rerun
    may replace it; its content hash decides whether it is reused), or, for ``report.json``, when
    it is a batch report. Raises :class:`InputError` naming the file and the take or actor.
    """
    from keyshape.manifest import ACTOR_FILES

    paths = [m.path]
    for a in m.actors.values():
        paths += [a.video, a.labels, a.model, a.targets, a.neutral, a.map, a.target_regions]
    paths += [t.video for t in m.takes]
    inputs = InputSet(paths, output=out)

    def ours(path: Path, owned: bool, who: str) -> None:
        inp = inputs.touched_by(path)
        if inp is not None:
            raise InputError(f"{who} would write {path.name} over or inside the input {inp}: give it another name "
                             "or choose another output folder", path)
        if (path.exists() or path.is_symlink()) and not owned:
            raise InputError(f"exists and was not written by keyshape batch ({who} writes it): move it away or "
                             "choose another output folder", path)

    def unchanged(path: Path, recorded: str | None, who: str) -> None:
        """A file batch wrote that the user changed since: never replaced; the run stops before work."""
        if recorded and path.is_file() and not path.is_symlink() and file_sha(path)["sha256"] != recorded:
            raise InputError(f"was changed since keyshape batch wrote it ({who}); batch does not replace your "
                             "edits: to discard them delete the file and rerun, or choose another output "
                             "folder", path)

    report = out / "report.json"
    try:
        is_report = json.loads(report.read_text()).get("format") == REPORT_FORMAT
    except (OSError, ValueError, AttributeError):
        is_report = False
    ours(report, is_report, "the batch report")
    for a in {t.actor for t in m.takes}:
        actor = m.actors[a]
        adir = actor_dir(out, a)
        rec = _batch_record(adir / RECORD)
        who = f"actor {a!r}"
        ours(adir / RECORD, rec is not None, who)
        rec = rec or {}
        if actor.model is None:
            ours(adir / "model.npz", "model_sha256" in rec, who)
        ours(adir / "keys.json", "keys_sha256" in rec, who)
        unchanged(adir / "keys.json", rec.get("keys_sha256"), who)
    for t in m.takes:
        tdir = take_dir(out, t)
        who = f"take {t.name!r} of actor {t.actor!r}"
        if t.name in ACTOR_FILES:
            raise InputError(f"{who}: the name is a file batch writes in the actor's folder", tdir)
        inp = inputs.touched_by(tdir)
        if inp is not None:
            raise InputError(f"{who} would write into the input {inp}: give the take another 'name' or choose "
                             "another output folder", tdir)
        rec = _batch_record(tdir / RECORD)
        ours(tdir / RECORD, rec is not None, who)
        rec = rec or {}
        ours(tdir / OUTPUT_FILES["tracks"], "tracks_sha256" in rec, who)
        ours(tdir / "tracks.meta.json", "tracks_sha256" in rec, who)
        unchanged(tdir / OUTPUT_FILES["tracks"], rec.get("tracks_sha256"), who)
        for o in m.settings.outputs:
            if o != "tracks":
                ours(tdir / OUTPUT_FILES[o], o in rec.get("outputs", {}) or o in rec.get("outputs_sha256", {}), who)


#: how long ``--scheduler`` keeps trying to reach the scheduler before the one-line error
CONNECT_TIMEOUT = "20s"


def _client(scheduler: str | None, workers: int | None, processes: bool):
    from distributed import Client, LocalCluster

    if scheduler:
        check_scheduler(scheduler)
        try:
            return Client(scheduler, timeout=CONNECT_TIMEOUT), None
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot connect "
                             f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    import dask
    from dask.system import CPU_COUNT     # the cores this process may use (affinity, cgroup quota)

    n = workers or CPU_COUNT or 1
    # one thread per worker, and its libraries' thread pools at one thread from the start: the variables
    # are set in each worker process before it imports numpy (Dask's own list, with FFmpeg's decoder added;
    # Dask's nanny sets them in this process's environment too, for the processes it spawns)
    env = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **ONE_THREAD_ENV}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": env}):
        # worker processes talk over TCP on this machine only; threads of this process use inproc://
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=processes, dashboard_address=":0",
                               **({"host": "127.0.0.1"} if processes else {}))
    return Client(cluster), cluster


def _dashboard(client) -> str | None:
    try:
        services = client.scheduler_info().get("services", {})
    except Exception:  # noqa: BLE001
        return None
    return client.dashboard_link if "dashboard" in services else None


def run_batch(manifest: str | Path | Manifest, out_dir: str | Path, scheduler: str | None = None,
              workers: int | None = None, processes: bool = True, show_progress: bool = True) -> dict:
    """Run the manifest's library into ``out_dir`` on Dask; return the report (also ``report.json``).

    Parameters
    ----------
    manifest : a manifest path or a read :class:`~keyshape.manifest.Manifest`
    scheduler : address of a running Dask scheduler (``tcp://HOST:PORT``); None starts a LocalCluster
    workers : LocalCluster workers (default: the machine's cores), one thread each
    processes : LocalCluster workers as processes (default) or threads of this process
    """
    from keyshape.base.progress import Progress

    global _CLIENT_PROCESS
    _CLIENT_PROCESS = True
    m = manifest if isinstance(manifest, Manifest) else read_manifest(manifest)
    out = Path(out_dir).resolve()
    check_layout(m, out)
    t0 = time.perf_counter()
    say = (lambda *a: print(*a, file=sys.stderr, flush=True)) if show_progress else (lambda *a: None)
    import secrets

    token_before = os.environ.get("KEYSHAPE_RUN_TOKEN")
    os.environ["KEYSHAPE_RUN_TOKEN"] = secrets.token_hex(4)     # this run's temporaries, workers' included
    try:
        client, cluster = _client(scheduler, workers, processes)   # nothing is created before this connects
    except BaseException:
        if token_before is None:
            os.environ.pop("KEYSHAPE_RUN_TOKEN", None)
        raise
    try:
        out.mkdir(parents=True, exist_ok=True)
        n_workers = len(client.scheduler_info().get("workers", {}))
        say(f"keyshape batch: {len(m.takes)} takes of {len(m.actors)} actors on "
            f"{scheduler or 'a local cluster'} ({n_workers} workers)")
        link = _dashboard(client)
        say(f"keyshape batch: Dask dashboard {link}" if link else
            "keyshape batch: no Dask dashboard (install bokeh where the scheduler runs to get one)")
        o = str(out)
        models = {a: client.submit(task_model, actor, o, key=f"model-{a}", pure=False)
                  for a, actor in m.actors.items()}
        tracks = [client.submit(task_track, t, m.actors[t.actor], m.settings, models[t.actor], o,
                                key=f"track-{t.actor}-{t.name}", pure=False) for t in m.takes]
        keys = {}
        for a, actor in m.actors.items():
            idx = [i for i, t in enumerate(m.takes) if t.actor == a]
            if idx:
                keys[a] = client.submit(task_keys, actor, [m.takes[i] for i in idx], [tracks[i] for i in idx], o,
                                        key=f"keys-{a}", pure=False)
        poses = {a: client.submit(task_poses, m.actors[a], k, o, key=f"poses-{a}", pure=False)
                 for a, k in keys.items()}
        finals = [client.submit(task_finish, t, m.actors[t.actor], m.settings, tracks[i], keys[t.actor], o,
                                poses[t.actor], key=f"finish-{t.actor}-{t.name}", pure=False)
                  for i, t in enumerate(m.takes)]
        from distributed import as_completed

        results: dict[str, dict] = {}
        n_frames = n_failed = 0
        with Progress(len(finals), desc="keyshape batch", unit="takes", enabled=show_progress, every=10.0) as prog:
            for fut in as_completed(finals):
                r = fut.result()
                results[fut.key] = r
                n_frames += r.get("stats", {}).get("frames", 0)
                n_failed += not r["ok"]
                prog.desc = f"keyshape batch ({n_frames} frames, {n_failed} failed)"
                prog.update()
        model_res = {a: f.result() for a, f in models.items()}
        keys_res = {a: f.result() for a, f in keys.items()}
        poses_res = {a: f.result() for a, f in poses.items()}
        spans = [{"task": f.key, **f.result()["span"]} for f in [*models.values(), *tracks, *keys.values(),
                                                                 *poses.values(), *finals]]
    except KeyboardInterrupt:
        client.close()
        if cluster is not None:
            cluster.close()
        remove_partials(out, m)
        raise
    finally:
        if client.status != "closed":
            client.close()
        if cluster is not None:
            cluster.close()
        if token_before is None:
            os.environ.pop("KEYSHAPE_RUN_TOKEN", None)
        else:
            os.environ["KEYSHAPE_RUN_TOKEN"] = token_before
    report = _report(m, out, scheduler, n_workers, processes, [results[f.key] for f in finals], model_res, keys_res,
                     time.perf_counter() - t0, poses_res)
    report["tasks"] = spans
    write_json(out / "report.json", report, end="\n")
    return report


def _report(m: Manifest, out: Path, scheduler, n_workers, processes, takes, models, keys, seconds,
            poses: dict | None = None) -> dict:
    rows = []
    for r in takes:
        st = r.get("stats", {})
        row = {"actor": r["actor"], "take": r["take"], "video": r["video"],
               "status": "failed" if not r["ok"] else ("skipped" if all(
                   s == "skipped" for s in r.get("stages", {}).values()) else "done"),
               "frames": st.get("frames"), "lost_frames": st.get("lost_frames"),
               "confidence": None if st.get("confidence") is None else round(st["confidence"], 4),
               "track_seconds": st.get("track_seconds"), "worker_max_rss_mb": st.get("worker_max_rss_mb"),
               "seconds": round(r.get("seconds", 0.0), 3),
               "finish_seconds": round(r.get("finish_seconds", 0.0), 3),
               "track_cpu_seconds": st.get("track_cpu_seconds"),
               "finish_cpu_seconds": round(r.get("finish_cpu_seconds", 0.0), 3), "stages": r.get("stages", {}),
               "outputs": r.get("outputs", {})}
        if st.get("warning"):
            row["warning"] = st["warning"]
        if not r["ok"]:
            row["error"] = r["error"]
        rows.append(row)
    actors = {}
    for a in m.actors:
        mr, kr = models[a], keys.get(a, {"ok": False, "error": "no takes"})
        actors[a] = {"model": mr.get("path"), "model_status": mr.get("status", "failed"),
                     "keys": kr.get("path"), "keys_status": kr.get("status", "failed"),
                     "keys_takes": kr.get("takes"), "keys_frame_offsets": kr.get("offsets"),
                     "model_seconds": round(mr.get("seconds", 0.0), 3), "keys_seconds": round(kr.get("seconds", 0.0), 3),
                     "model_cpu_seconds": round(mr.get("cpu_seconds", 0.0), 3),
                     "keys_cpu_seconds": round(kr.get("cpu_seconds", 0.0), 3)}
        pr = (poses or {}).get(a)
        if m.actors[a].rig is not None and pr is not None:
            actors[a].update(poses=pr.get("path"), poses_status=pr.get("status", "failed"))
        for name, res in (("model_error", mr), ("keys_error", kr), ("poses_error", pr or {"ok": True})):
            if not res["ok"]:
                actors[a][name] = res["error"]
    failed = [r for r in rows if r["status"] == "failed"]
    return {"format": REPORT_FORMAT, "version": 1, "manifest": str(m.path), "out_dir": str(out),
            "scheduler": scheduler or ("LocalCluster (processes)" if processes else "LocalCluster (threads)"),
            "workers": n_workers, "seconds": round(seconds, 3), "takes": rows, "actors": actors,
            "n_takes": len(rows), "n_done": sum(r["status"] == "done" for r in rows),
            "n_skipped": sum(r["status"] == "skipped" for r in rows), "n_failed": len(failed),
            "frames": int(sum(r["frames"] or 0 for r in rows))}


# ---------------------------------------------------------------- the command

def register(subparsers) -> None:
    p = subparsers.add_parser(
        "batch", help="run a footage library (TOML manifest) through the video path on Dask, resumably",
        description="Train each actor's tracker once, track every take in parallel, choose one key set per "
                    "actor over all its takes, decompose and retarget every take in parallel; outputs in "
                    "OUT_DIR/<actor>/<take>/, key sets in OUT_DIR/<actor>/keys.json, the summary in "
                    "OUT_DIR/report.json. A rerun skips what has not changed. See README: Batch.")
    p.add_argument("manifest", help="project manifest (TOML)")
    p.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="output folder")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="use a running Dask scheduler (default: a local cluster on this machine)")
    p.add_argument("--workers", type=int, default=None,
                   help="local cluster workers, one thread each (default: the number of cores)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    if args.scheduler and args.workers:
        raise InputError("--workers is for the local cluster; not with --scheduler")
    check_scheduler(args.scheduler)
    rep = run_batch(args.manifest, args.output, scheduler=args.scheduler, workers=args.workers,
                    processes=PROCESSES, show_progress=not args.quiet)
    print(f"keyshape batch: {rep['n_takes']} takes ({rep['n_done']} done, {rep['n_skipped']} skipped, "
          f"{rep['n_failed']} failed), {rep['frames']} frames in {rep['seconds']:.1f} s -> "
          f"{Path(rep['out_dir']) / 'report.json'}")
    for r in rep["takes"]:
        if r.get("warning"):
            print(f"keyshape batch: warning: {r['actor']}/{r['take']}: {r['warning']}", file=sys.stderr)
        if r["status"] == "failed":
            print(f"keyshape batch: {r['actor']}/{r['take']} failed: {r['error']}", file=sys.stderr)
    return 1 if rep["n_failed"] else 0
