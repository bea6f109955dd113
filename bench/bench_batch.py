"""Does ``keyshape batch`` scale with cores? One worker on one core against two workers on two cores, the same
library in the same run (issue 26). Prints the ratio beside the load average and the CPU time each run
got; asserts nothing.

    python bench/bench_batch.py                   # 2 actors x 4 takes x 750 frames: about 2.5 min on 2 idle cores
    python bench/bench_batch.py --all             # also serial commands, thread workers, 1 worker on all cores
    python bench/bench_batch.py [--actors 2] [--takes 4] [--frames 750] [--clip 150] [--library DIR]

The library (``bench/synth_library.py``: one synthetic person per actor) is
synthesised with ``--clip`` frames per take, then every take is lengthened to ``--frames`` by playing
its clip forwards and backwards (continuous motion; synthesis costs ~20 ms a frame, tracking ~4): the
work per run must dwarf the fixed start-up (the cluster, each worker's imports: a few seconds) for
a ratio to mean anything. ``--library DIR`` keeps the library for later runs.

Each configuration is the command itself, ``keyshape batch MANIFEST -o OUT --workers N --quiet``, in a
fresh output folder, run as a child process whose CPU affinity is the first N cores of this one
(``os.sched_setaffinity``, inherited by the cluster's worker processes): a worker's tracking task decodes
ahead on a second thread, so an unconfined single worker takes part of the second core too (``--all``
shows it) and ``--workers 1`` against ``--workers 2`` would not be one core against two. Per run:
wall seconds, the CPU seconds of the whole process tree (``os.wait4``), cores busy (CPU / wall), the load
average before and after (``os.getloadavg``: on an idle machine it is below 0.5 before the first
run), and from ``report.json``'s task spans how much of the wall time the tasks covered (the rest is
start-up and scheduling) and how much CPU the workers' other threads took. On a loaded machine the
2-core run gets less than two cores: read the ratio with the CPU time and the load beside it.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

KEYSHAPE = [sys.executable, "-m", "keyshape"]
#: ``keyshape`` with the batch's local cluster workers as threads of one process
THREADS_MAIN = ("import sys, keyshape.batch as b; from keyshape.cli import main; b.PROCESSES = False; "
                "sys.exit(main(sys.argv[1:]))")


def run(cmd: list[str]) -> None:
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def lengthen(path: Path, clip: int, frames: int) -> None:
    """Rewrite the take at ``path`` as ``frames`` frames: its first ``clip`` frames forwards, backwards,
    forwards, ... (no jump for the tracker to lose the face at)."""
    from keyshape.base.formats.video import VideoReader, video_info, video_writer

    info = video_info(path)
    if info.n_frames == frames:
        return
    imgs = [img for i, img in VideoReader(path) if i < clip]
    cycle = list(range(len(imgs))) + list(range(len(imgs) - 2, 0, -1))
    with video_writer(path, info.fps, (info.width, info.height)) as w:
        for i in range(frames):
            w.write(imgs[cycle[i % len(cycle)]])


def library(folder: Path, actors: int, takes: int, clip: int, frames: int) -> Path:
    from synth_library import synth_library

    manifest = synth_library(folder, actors=actors, takes=takes, frames=clip, keys=8)
    for p in sorted(folder.glob("actor*/take*.mp4")):
        lengthen(p, clip, frames)
    return manifest


def cores() -> list[int] | None:
    """The cores this process may run on (None where affinity cannot be set)."""
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_setaffinity") else None


def batch_command(manifest: Path, out: Path, workers: int, affinity: list[int] | None,
                  threads: bool = False) -> dict:
    """``keyshape batch`` as a child process confined to ``affinity``: wall, CPU of its tree, load, report."""
    # thread workers: keyshape.batch.PROCESSES set to False in the child (no option on the command line)
    start = KEYSHAPE if not threads else [sys.executable, "-c", THREADS_MAIN]
    cmd = start + ["batch", str(manifest), "-o", str(out), "--workers", str(workers), "--quiet"]
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=(lambda: os.sched_setaffinity(0, affinity)) if affinity else None)
    _, status, usage = os.wait4(proc.pid, 0)     # the child and every process it waited for (its workers)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode(errors="replace")
    proc.stderr.close()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"keyshape batch failed:\n{err}")
    rep = json.loads((out / "report.json").read_text())
    assert rep["n_failed"] == 0, [r.get("error") for r in rep["takes"]]
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "load": (load0, os.getloadavg()[0]), "report": rep}


def spans(rep: dict) -> dict:
    """From the report's task spans: the window the tasks covered, their CPU, the task threads' CPU, and the
    seconds during which two or more workers were busy."""
    s = rep["tasks"]
    start, end = min(t["start"] for t in s), max(t["end"] for t in s)
    edges = sorted([(t["start"], 1) for t in s] + [(t["end"], -1) for t in s])
    both, busy, prev = 0.0, 0, start
    for x, d in edges:
        both += (x - prev) if busy >= 2 else 0.0
        busy, prev = busy + d, x
    return {"window": end - start, "cpu": sum(t["cpu"] for t in s), "thread_cpu": sum(t["thread_cpu"] for t in s),
            "two_busy": both}


def serial(manifest: Path, out: Path) -> float:
    """The commands one after another, each its own process as a user would type them."""
    from keyshape.manifest import read_manifest

    m = read_manifest(manifest)
    s = m.settings
    t0 = time.perf_counter()
    for name, actor in m.actors.items():
        adir = out / name
        adir.mkdir(parents=True, exist_ok=True)
        run(KEYSHAPE + ["train", str(actor.video), "--labels", str(actor.labels), "--morphs", str(actor.morphs),
                        "-o", str(adir / "model.npz")])
        takes = [t for t in m.takes if t.actor == name]
        for t in takes:
            run(KEYSHAPE + ["track", str(t.video), "--model", str(adir / "model.npz"), "-o",
                            str(adir / t.name / "tracks.csv"), "--quiet", "--jobs", "1"])   # one process, as batch's
        code = ("import sys; from keyshape import api; ts=[api.read_tracks(p) for p in sys.argv[4:]]; "
                "api.select(ts, int(sys.argv[1]), sys.argv[2], ['mouth', 'eyes']).save(sys.argv[3])")
        run([sys.executable, "-c", code, str(actor.keys), actor.selector, str(adir / "keys.json")]
            + [str(adir / t.name / "tracks.csv") for t in takes])
        for t in takes:
            d = adir / t.name
            run(KEYSHAPE + ["decompose", str(d / "tracks.csv"), "--keys", str(adir / "keys.json"), "--solver",
                            s.solver, "--ridge", str(s.ridge), "-o", str(d / "weights.csv")])
            for o in ("animation.glb", "curves.csv"):
                run(KEYSHAPE + ["retarget", str(d / "weights.csv"), "--targets", str(actor.targets), "--regions",
                                str(actor.target_regions), "--tracks", str(d / "tracks.csv"), "-o", str(d / o)])
    return time.perf_counter() - t0


def makespan(rep: dict, workers: int) -> float:
    """Seconds the batch's graph would take on ``workers`` idle cores, from its tasks' measured CPU
    seconds (list scheduling in submission order, as Dask's priorities; no start-up, no I/O wait)."""
    tasks = [(("model", a), (), v["model_cpu_seconds"]) for a, v in rep["actors"].items()]
    tasks += [(("track", r["actor"], r["take"]), (("model", r["actor"]),), r["track_cpu_seconds"])
              for r in rep["takes"]]
    tasks += [(("keys", a), tuple(("track", a, r["take"]) for r in rep["takes"] if r["actor"] == a),
               v["keys_cpu_seconds"]) for a, v in rep["actors"].items()]
    tasks += [(("finish", r["actor"], r["take"]), (("track", r["actor"], r["take"]), ("keys", r["actor"])),
               r["finish_cpu_seconds"]) for r in rep["takes"]]
    done: dict = {}
    free = [0.0] * workers
    todo = list(tasks)
    while todo:
        i = min(range(workers), key=free.__getitem__)
        now = free[i]
        ready = [t for t in todo if all(d in done and done[d] <= now for d in t[1])]
        if not ready:
            free[i] = min(v for v in done.values() if v > now)
            continue
        name, _, cpu = ready[0]
        done[name] = now + cpu
        free[i] = done[name]
        todo.remove(ready[0])
    return max(done.values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--actors", type=int, default=2)
    ap.add_argument("--takes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=750, help="frames per take (default 750)")
    ap.add_argument("--clip", type=int, default=150, help="frames synthesised per take, played back and forth")
    ap.add_argument("--library", default=None, help="folder to keep the synthetic library in (default: temporary)")
    ap.add_argument("--all", action="store_true",
                    help="also the serial commands, 1 and 2 thread workers, and 1 worker on all cores")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    lib = Path(args.library) if args.library else tmp / "library"
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        manifest = library(lib, args.actors, args.takes, min(args.clip, args.frames), args.frames)
        n_frames = args.actors * args.takes * args.frames
        cpus = cores()
        print(f"library: {args.actors} actors x {args.takes} takes x {args.frames} frames = {n_frames} frames "
              f"(640x480), ready in {time.perf_counter() - t0:.0f} s ({time.process_time() - c0:.0f} s CPU); this "
              f"process may run on cores {cpus} of {os.cpu_count()}; load average {os.getloadavg()[0]:.2f}", flush=True)
        if cpus is not None and len(cpus) < 2:
            print("only one core here: the 2-core run shares it (no scaling to measure)")
        confs = [("1 worker, 1 core", 1, cpus[:1] if cpus else None, False),
                 ("2 workers, 2 cores", 2, cpus[:2] if cpus else None, False)]
        if args.all:
            confs += [("1 worker, all cores", 1, None, False),
                      ("1 thread worker, 1 core", 1, cpus[:1] if cpus else None, True),
                      ("2 thread workers, 2 cores", 2, cpus[:2] if cpus else None, True)]
        runs = {}
        for label, n, aff, threads in confs:
            runs[label] = r = batch_command(manifest, tmp / label.replace(" ", "_").replace(",", ""), n, aff, threads)
            print(f"  {label}: {r['wall']:.1f} s, CPU {r['cpu']:.1f} s, load {r['load'][0]:.2f} -> {r['load'][1]:.2f}",
                  flush=True)
        if args.all:
            t = serial(manifest, tmp / "serial")
            print(f"  serial commands (one process per command, all cores): {t:.1f} s", flush=True)
            runs["serial commands"] = {"wall": t, "cpu": float("nan"), "load": (float("nan"), os.getloadavg()[0])}
            label = "rerun of the 2-worker batch, all skipped"
            r = batch_command(manifest, tmp / "2_workers_2_cores", 2, cpus[:2] if cpus else None)
            assert r["report"]["n_skipped"] == r["report"]["n_takes"], r["report"]
            runs[label] = r

        one = runs["1 worker, 1 core"]
        print(f"\n{'configuration':42s} {'wall s':>7s} {'CPU s':>7s} {'cores busy':>10s} {'load before/after':>18s}"
              f" {'speed-up':>8s}  tasks' window / CPU / other threads' CPU / 2+ workers busy")
        for label, r in runs.items():
            row = f"  {label:40s} {r['wall']:7.1f} {r['cpu']:7.1f} {r['cpu'] / r['wall']:10.2f} " \
                  f"{r['load'][0]:8.2f} / {r['load'][1]:5.2f}   {one['wall'] / r['wall']:6.2f}x"
            if "report" in r:
                s = spans(r["report"])
                row += f"  {s['window']:.1f} s / {s['cpu']:.1f} s / {s['cpu'] - s['thread_cpu']:.1f} s / " \
                       f"{s['two_busy']:.1f} s"
            print(row)
        two = runs["2 workers, 2 cores"]
        print(f"\n2 workers on 2 cores / 1 worker on 1 core: {one['wall'] / two['wall']:.2f}x wall "
              f"(aim >= 1.7x on an idle machine); CPU time {one['cpu']:.1f} s and {two['cpu']:.1f} s; load average "
              f"{one['load'][0]:.2f} before the first run, {two['load'][1]:.2f} after the second; "
              + ("idle enough to judge" if max(one["load"][0], two["load"][0]) < 0.5 else
                 "NOT idle: the ratio is not the figure to judge"))

        for label, r in runs.items():     # the same work: CPU per frame should match across runs on idle cores
            if "report" in r and label != "rerun of the 2-worker batch, all skipped":
                t = r["report"]["takes"]
                track = 1000 * sum(x["track_cpu_seconds"] for x in t) / n_frames
                finish = 1000 * sum(x["finish_cpu_seconds"] for x in t) / n_frames
                print(f"  {label}: CPU per frame in the tasks: track {track:.2f} ms, decompose+retarget {finish:.2f} ms")
        rep = one["report"]
        cpu_track = sum(r["track_cpu_seconds"] for r in rep["takes"])
        cpu_finish = sum(r["finish_cpu_seconds"] for r in rep["takes"])
        print(f"CPU time inside the tasks (1 worker): track {1000 * cpu_track / n_frames:.2f} ms/frame (decode "
              f"included), decompose+retarget {1000 * cpu_finish / n_frames:.2f} ms/frame, train "
              f"{sum(a['model_cpu_seconds'] for a in rep['actors'].values()) / args.actors:.1f} s per actor, key "
              f"selection {sum(a['keys_cpu_seconds'] for a in rep['actors'].values()) / args.actors:.2f} s per actor; "
              f"worker peak memory {max(r['worker_max_rss_mb'] or 0 for r in rep['takes']):.0f} MiB")
        one_ideal, two_ideal = makespan(rep, 1), makespan(rep, 2)
        print(f"the graph on idle cores, from these CPU times (a model, not a measurement): 1 worker {one_ideal:.1f} s, "
              f"2 workers {two_ideal:.1f} s: ceiling {one_ideal / two_ideal:.2f}x before start-up and I/O")
        out = tmp / "1_worker_1_core"
        sizes = {name: sum(p.stat().st_size for p in out.rglob(name)) / n_frames
                 for name in ("tracks.csv", "weights.csv", "animation.glb", "curves.csv")}
        videos = sum(p.stat().st_size for p in lib.glob("actor*/take*.mp4")) / n_frames
        models = sum(p.stat().st_size for p in out.glob("*/model.npz")) / args.actors
        print(f"bytes per frame: video {videos:.0f} (mp4v 640x480), " +
              ", ".join(f"{k} {v:.0f}" for k, v in sizes.items()) + f"; model.npz {models / 1e6:.1f} MB per actor")
        print(json.dumps({"seconds": {k: round(v["wall"], 2) for k, v in runs.items()},
                          "cpu_seconds": {k: round(v["cpu"], 2) for k, v in runs.items()},
                          "ratio_2_to_1": round(one["wall"] / two["wall"], 3)}))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
