"""``keyshape batch`` on a synthetic library: 1 vs 2 workers, processes vs threads, against the serial
command-by-command baseline, all measured in one run (issue 15). Prints ratios; asserts nothing.

    python bench/bench_batch.py [--actors 3] [--takes 8] [--frames 600] [--library DIR]

The library (``keyshape.data_synth.library.synth_library``: one synthetic person per actor, its
footage cut into takes) is kept in ``--library`` and reused by later runs. Synthesis costs about
0.1 s per 640x480 frame on one core, so the issue's 3 x 8 x 600 library takes ~25 minutes to
make; ``--takes 4 --frames 150`` is the size that fits a shared 2-core machine.

Configurations, each into a fresh output folder (nothing to skip):
- serial: the commands one after another, each its own process as a user would type them
  (``keyshape train``, ``keyshape track`` per take, the per-actor key selection through
  ``keyshape.api.select`` since no single command selects over several takes,
  ``keyshape decompose`` and ``keyshape retarget`` per take);
- batch with a LocalCluster of 1 and 2 worker processes, and of 1 and 2 worker threads;
- a rerun of the 2-process batch on its own output (everything skipped).
It also prints per-frame and per-actor costs and the bytes per frame of each stage's files, the
figures docs/scale.md scales up.
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


def run(cmd: list[str]) -> None:
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def serial(manifest: Path, out: Path) -> float:
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
                            str(adir / t.name / "tracks.csv"), "--quiet"])
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


def batch(manifest: Path, out: Path, workers: int, processes: bool) -> tuple[float, dict]:
    from keyshape.batch import run_batch

    t0 = time.perf_counter()
    rep = run_batch(manifest, out, workers=workers, processes=processes, show_progress=False)
    assert rep["n_failed"] == 0, [r.get("error") for r in rep["takes"]]
    return time.perf_counter() - t0, rep


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
    ap.add_argument("--actors", type=int, default=3)
    ap.add_argument("--takes", type=int, default=8)
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--library", default=None, help="folder to keep the synthetic library in (default: temporary)")
    args = ap.parse_args()
    from keyshape.data_synth.library import synth_library

    tmp = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    lib = Path(args.library) if args.library else tmp / "library"
    try:
        t0 = time.perf_counter()
        manifest = synth_library(lib, actors=args.actors, takes=args.takes, frames=args.frames, keys=8)
        n_frames = args.actors * args.takes * args.frames
        print(f"library: {args.actors} actors x {args.takes} takes x {args.frames} frames = {n_frames} frames "
              f"(640x480), ready in {time.perf_counter() - t0:.0f} s; {os.cpu_count()} cores (shared machine: "
              f"timings are noisy, compare ratios within this run)")
        times, reports = {}, {}
        times["serial commands"] = serial(manifest, tmp / "serial")
        print(f"  serial commands: {times['serial commands']:.1f} s", flush=True)
        for label, workers, processes in (("batch 1 process", 1, True), ("batch 2 processes", 2, True),
                                          ("batch 1 thread", 1, False), ("batch 2 threads", 2, False)):
            times[label], reports[label] = batch(manifest, tmp / label.replace(" ", "_"), workers, processes)
            print(f"  {label}: {times[label]:.1f} s", flush=True)
        label = "rerun, all skipped (2 processes)"
        times[label], rep = batch(manifest, tmp / "batch_2_processes", 2, True)
        assert rep["n_skipped"] == rep["n_takes"], rep
        print(f"  {label}: {times[label]:.1f} s")

        base = times["serial commands"]
        one = times["batch 1 process"]
        print("\nconfiguration                        seconds   vs serial   vs batch 1 process")
        for label, t in times.items():
            print(f"  {label:34s} {t:7.1f}   {base / t:8.2f}x   {one / t:8.2f}x")

        rep = reports["batch 1 process"]
        track = sum(r["track_seconds"] for r in rep["takes"])
        finish = sum(r["finish_seconds"] for r in rep["takes"])
        train = [a["model_seconds"] for a in rep["actors"].values()]
        keys = [a["keys_seconds"] for a in rep["actors"].values()]
        rss = max(r["worker_max_rss_mb"] or 0 for r in rep["takes"])
        print(f"\nper-frame costs (batch, 1 worker process): track {1000 * track / n_frames:.2f} ms/frame "
              f"(decode included), decompose+retarget {1000 * finish / n_frames:.2f} ms/frame; "
              f"train {sum(train) / len(train):.1f} s per actor; key selection {sum(keys) / len(keys):.2f} s per "
              f"actor over {args.takes * args.frames} frames; worker peak memory {rss:.0f} MiB")
        cpu_track = sum(r["track_cpu_seconds"] for r in rep["takes"])
        cpu_finish = sum(r["finish_cpu_seconds"] for r in rep["takes"])
        print(f"CPU time (excludes waiting for the shared cores): track {1000 * cpu_track / n_frames:.2f} ms/frame, "
              f"decompose+retarget {1000 * cpu_finish / n_frames:.2f} ms/frame, train "
              f"{sum(a['model_cpu_seconds'] for a in rep['actors'].values()) / args.actors:.1f} s per actor, key "
              f"selection {sum(a['keys_cpu_seconds'] for a in rep['actors'].values()) / args.actors:.2f} s per actor")
        one_ideal, two_ideal = makespan(rep, 1), makespan(rep, 2)
        print(f"the graph on idle cores, from these CPU times (a model, not a measurement): 1 worker "
              f"{one_ideal:.1f} s, 2 workers {two_ideal:.1f} s: ceiling {one_ideal / two_ideal:.2f}x "
              f"(Dask start-up and I/O not included)")
        from keyshape.base.formats.video import VideoReader
        t0 = time.perf_counter()
        n_dec = sum(1 for p in sorted(lib.glob("actor0/take*.mp4")) for _ in VideoReader(p))
        print(f"decode alone: {1000 * (time.perf_counter() - t0) / n_dec:.2f} ms/frame (640x480 mp4v, wall)")
        out = tmp / "batch_1_process"
        sizes = {}
        for name in ("tracks.csv", "weights.csv", "animation.glb", "curves.csv"):
            sizes[name] = sum(p.stat().st_size for p in out.rglob(name)) / n_frames
        videos = sum(p.stat().st_size for p in lib.glob("actor*/take*.mp4")) / n_frames
        models = sum(p.stat().st_size for p in out.glob("*/model.npz")) / args.actors
        print(f"bytes per frame: video {videos:.0f} (mp4v 640x480), " +
              ", ".join(f"{k} {v:.0f}" for k, v in sizes.items()) + f"; model.npz {models / 1e6:.1f} MB per actor")
        print(json.dumps({"times_s": {k: round(v, 2) for k, v in times.items()}}))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
