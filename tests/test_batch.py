"""``keyshape batch``: a synthetic library (2 actors x 2 takes x :data:`FRAMES` frames) on Dask; outputs identical to
the API run one take at a time; resume and skip; failing takes reported; the manifest's schema check;
and (marked slow: CI runs them) a real ``dask scheduler`` + ``dask worker`` pair on 127.0.0.1 and Ctrl-C."""
from __future__ import annotations

import filecmp
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import sigint_as_a_terminal_gives_it

from keyshape.base.errors import InputError
from keyshape.batch import run_batch
from keyshape.cli import main
from keyshape.manifest import read_manifest

COMPARED = ("tracks.csv", "weights.csv", "animation.glb", "curves.csv")
#: frames per take of the synthetic library (what the tests prove holds at any length)
FRAMES = 30
#: the rig library's shapes (of the shipped ICT-FaceKit subset's 53: what the tests prove holds for any rig)
RIG_SHAPES = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R",
              "mouthFunnel"]


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> Path:
    from synth_library import synth_library

    return synth_library(tmp_path_factory.mktemp("library"), actors=2, takes=2, frames=FRAMES, keys=4, morphs=30,
                         size=(320, 240))


@pytest.fixture(scope="module")
def first_run(library, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch") / "out"
    report = run_batch(library, out, workers=2, show_progress=False)
    return out, report


def test_every_output_and_a_report(first_run):
    out, report = first_run
    assert report["n_takes"] == 4 and report["n_done"] == 4 and report["n_failed"] == 0, report
    assert report["workers"] == 2 and report["frames"] == 4 * FRAMES
    for row in report["takes"]:
        assert row["frames"] == FRAMES and row["lost_frames"] == 0 and 0.9 < row["confidence"] <= 1.0, row
        assert row["stages"] == {"track": "tracked", "finish": "done"}
        assert sorted(row["outputs"]) == ["curves", "glb", "tracks", "weights"]
        for name in COMPARED:
            assert (out / row["actor"] / row["take"] / name).stat().st_size > 0
    for a in ("actor0", "actor1"):
        assert report["actors"][a]["model_status"] == "trained"
        assert report["actors"][a]["keys_takes"] == ["take00", "take01"]
        assert report["actors"][a]["keys_frame_offsets"] == [0, FRAMES]
        keys = json.loads((out / a / "keys.json").read_text())
        assert sorted(keys["regions"]) == ["eyes", "mouth"]
        assert all(len(r["keys"]) == 4 for r in keys["regions"].values())
    assert json.loads((out / "report.json").read_text()) == report
    assert not list(out.rglob("*.partial*"))


def test_identical_to_the_api_one_take_at_a_time(library, first_run, tmp_path):
    """The serial reference: the API step by step, with the files between steps as the commands have them."""
    from keyshape import api
    from keyshape.base.formats.tracks import read_tracks, write_tracks

    out, _ = first_run
    m = read_manifest(library)
    s = m.settings
    for name, actor in m.actors.items():
        model = api.train(actor.video, actor.labels, scheme=actor.scheme, components=actor.components,
                          morphs=actor.morphs, seed=actor.seed)
        model.save(tmp_path / name / "model.npz")
        model = api.AppearanceModel.load(tmp_path / name / "model.npz")
        takes = [t for t in m.takes if t.actor == name]
        for t in takes:
            write_tracks(tmp_path / name / t.name / "tracks.csv", api.track(t.video, model, smooth=s.smooth))
        tracks = [read_tracks(tmp_path / name / t.name / "tracks.csv") for t in takes]
        api.select(tracks, actor.keys, actor.selector, actor.regions, seed=actor.seed).save(tmp_path / name / "k.json")
        keys = api.Keys.load(tmp_path / name / "k.json")
        assert filecmp.cmp(tmp_path / name / "k.json", out / name / "keys.json", shallow=False), name
        for t, tr in zip(takes, tracks):
            d = tmp_path / name / t.name
            api.decompose(tr, keys, s.solver, s.ridge, s.smooth_lambda).save(d / "weights.csv")
            anim = api.retarget(api.Weights.load(d / "weights.csv"), actor.targets, actor.target_regions, tracks=tr)
            anim.export(d / "animation.glb")
            anim.export(d / "curves.csv")
            for f in COMPARED:
                assert filecmp.cmp(d / f, out / name / t.name / f, shallow=False), (name, t.name, f)


def keys_content(path) -> dict:
    """KEYS.json without ``source`` (the command names the tracks files it read; the batch's own)."""
    data = json.loads(Path(path).read_text())
    data.pop("source", None)
    return data


def test_identical_to_the_commands(library, first_run, tmp_path):
    """``keyshape train/track/select/decompose/retarget`` one after another, with no option beyond the
    manifest's, give the batch's files byte for byte (the key set: the same content, one selection
    over both takes)."""
    out, _ = first_run
    m = read_manifest(library)
    actor = m.actors["actor1"]
    takes = [t for t in m.takes if t.actor == "actor1"]
    assert [t.name for t in takes] == ["take00", "take01"]
    assert main(["train", str(actor.video), "--labels", str(actor.labels), "--morphs", str(actor.morphs),
                 "-o", str(tmp_path / "model.npz")]) == 0
    for t in takes:
        assert main(["track", str(t.video), "--model", str(tmp_path / "model.npz"),
                     "-o", str(tmp_path / f"{t.name}.csv"), "--quiet"]) == 0
    assert main(["select", *[str(tmp_path / f"{t.name}.csv") for t in takes], "-k", str(actor.keys),
                 *[a for r in actor.regions for a in ("--region", r)], "-o", str(tmp_path / "keys.json")]) == 0
    assert keys_content(tmp_path / "keys.json") == keys_content(out / "actor1" / "keys.json")
    take = takes[1]
    assert main(["decompose", str(tmp_path / f"{take.name}.csv"), "--keys", str(tmp_path / "keys.json"),
                 "-o", str(tmp_path / "weights.csv")]) == 0
    for name in ("animation.glb", "curves.csv"):
        assert main(["retarget", str(tmp_path / "weights.csv"), "--targets", str(actor.targets), "--regions",
                     str(actor.target_regions), "--tracks", str(tmp_path / f"{take.name}.csv"),
                     "-o", str(tmp_path / name)]) == 0
    (tmp_path / "tracks.csv").write_bytes((tmp_path / f"{take.name}.csv").read_bytes())
    for name in COMPARED:
        assert filecmp.cmp(tmp_path / name, out / "actor1" / take.name / name, shallow=False), name


def test_a_rig_library_writes_curves_and_live_link_resumably_as_the_commands_do(library, first_run, tmp_path):
    """Two actors driving a rig (a small one from the shipped ICT-FaceKit subset): one pose library per
    actor (fitted once for the artist, or the manifest's corrected one), each take's rig curves, Live Link
    CSV and .glb, as ``keyshape pose`` and ``keyshape solve`` give them (``solve --poses --weights`` with a
    corrected library); a rerun skips everything."""
    from keyshape.data_synth.library import ict_subset_rig

    out0, _ = first_run
    lib = library.parent
    rig, lm = ict_subset_rig(tmp_path / "rig", names=RIG_SHAPES)
    text = "[settings]\noutputs = [\"curves\", \"livelink\", \"glb\", \"preview\"]\n\n"
    for a in ("actor0", "actor1"):
        text += (f'[actors.{a}]\nmodel = "{out0 / a / "model.npz"}"\nkeys = 4\nregions = ["mouth", "eyes"]\n'
                 f'rig = "{rig}"\nlandmarks = "{lm}"\n\n')
    for a in ("actor0", "actor1"):
        for t in ("take00", "take01"):
            text += f'[[takes]]\nactor = "{a}"\nvideo = "{lib / a / t}.mp4"\n\n'
    manifest = tmp_path / "rig.toml"
    manifest.write_text(text)
    out = tmp_path / "out"
    rep = run_batch(manifest, out, workers=2, processes=False, show_progress=False)
    assert rep["n_done"] == 4 and rep["n_failed"] == 0, rep["takes"]
    for a in ("actor0", "actor1"):
        assert rep["actors"][a]["poses_status"] == "fitted" and (out / a / "poses.json").is_file()
        for t in ("take00", "take01"):
            d = out / a / t
            assert sorted(rep_row(rep, a, t)["outputs"]) == ["curves", "glb", "livelink", "preview", "tracks",
                                                             "weights"]
            from keyshape.base.formats.video import video_info
            assert video_info(d / "preview.mp4").n_frames == FRAMES
            assert (d / "curves.csv").read_text().startswith("frame,")
            assert (d / "livelink.csv").read_text().startswith("Timecode,BlendShapeCount,")
            assert (d / "animation.glb").stat().st_size > 0
    # the commands, one after another, give the same files
    d = out / "actor1" / "take01"
    assert main(["pose", str(out / "actor1" / "keys.json"), "--rig", str(rig), "--landmarks", str(lm),
                 "-o", str(tmp_path / "poses.json")]) == 0
    poses = json.loads((tmp_path / "poses.json").read_text())
    batch_poses = json.loads((out / "actor1" / "poses.json").read_text())
    assert {k: v for k, v in poses.items() if k != "keys"} == {k: v for k, v in batch_poses.items() if k != "keys"}
    for name, extra in (("curves.csv", []), ("livelink.csv", ["--livelink"]), ("animation.glb", [])):
        assert main(["solve", str(d / "tracks.csv"), "--keys", str(out / "actor1" / "keys.json"), "--rig", str(rig),
                     "--landmarks", str(lm), *extra, "-o", str(tmp_path / name)]) == 0
        assert filecmp.cmp(tmp_path / name, d / name, shallow=False), name
    # resumable: nothing recomputed; a corrected pose library given in the manifest redoes only the curves
    rep = run_batch(manifest, out, workers=1, processes=False, show_progress=False)
    assert rep["n_skipped"] == 4 and {a["poses_status"] for a in rep["actors"].values()} == {"skipped"}, rep
    fixed = json.loads((out / "actor0" / "poses.json").read_text())
    key = next(iter(fixed["regions"]["mouth"]["keys"]))
    fixed["regions"]["mouth"]["keys"][key] = {"jawOpen": 1.0}
    (tmp_path / "fixed.json").write_text(json.dumps(fixed))
    manifest.write_text(text.replace(f'[actors.actor0]\nmodel = "{out0 / "actor0" / "model.npz"}"\n',
                                     f'[actors.actor0]\nmodel = "{out0 / "actor0" / "model.npz"}"\n'
                                     f'poses = "{tmp_path / "fixed.json"}"\n'))
    before = (out / "actor1" / "take00" / "curves.csv").read_bytes()
    rep = run_batch(manifest, out, workers=1, processes=False, show_progress=False)
    stages = {(r["actor"], r["take"]): r["stages"] for r in rep["takes"]}
    assert stages[("actor0", "take00")] == {"track": "skipped", "finish": "done"}, stages
    assert stages[("actor1", "take00")] == {"track": "skipped", "finish": "skipped"}, stages
    assert rep["actors"]["actor0"]["poses_status"] == "given"
    assert (out / "actor1" / "take00" / "curves.csv").read_bytes() == before
    d0 = out / "actor0" / "take00"
    assert main(["solve", str(d0 / "tracks.csv"), "--keys", str(out / "actor0" / "keys.json"), "--rig", str(rig),
                 "--landmarks", str(lm), "--poses", str(tmp_path / "fixed.json"), "--weights", str(d0 / "weights.csv"),
                 "-o", str(tmp_path / "fixed_curves.csv")]) == 0
    assert filecmp.cmp(tmp_path / "fixed_curves.csv", d0 / "curves.csv", shallow=False)
    # issue 37: the artist corrects OUT/actor1/poses.json in pose-edit; a rerun keeps it and uses it
    edited = json.loads((out / "actor1" / "poses.json").read_text())
    key = next(iter(edited["regions"]["mouth"]["keys"]))
    edited["regions"]["mouth"]["keys"][key] = {"jawOpen": 0.5}
    (out / "actor1" / "poses.json").write_text(json.dumps(edited))
    kept = (out / "actor1" / "poses.json").read_bytes()
    rep = run_batch(manifest, out, workers=1, processes=False, show_progress=False)
    assert rep["actors"]["actor1"]["poses_status"] == "edited", rep["actors"]
    assert (out / "actor1" / "poses.json").read_bytes() == kept
    stages = {(r["actor"], r["take"]): r["stages"] for r in rep["takes"]}
    assert stages[("actor1", "take00")] == {"track": "skipped", "finish": "done"}, stages


def test_the_report_says_when_and_where_each_task_ran(first_run):
    """One span per task (2 trainings, 4 tracks, 2 key selections, 2 pose steps, 4 finishes), in worker
    processes (not this one), with the worker process's CPU at least its task thread's."""
    _, report = first_run
    spans = report["tasks"]
    assert sorted(s["task"].split("-")[0] for s in spans) == sorted(["model"] * 2 + ["track"] * 4 + ["keys"] * 2
                                                                    + ["poses"] * 2 + ["finish"] * 4)
    assert len({s["pid"] for s in spans}) <= 2 and os.getpid() not in {s["pid"] for s in spans}
    for s in spans:
        assert s["start"] <= s["end"] and s["cpu"] >= s["thread_cpu"] - 0.01 >= -0.01, s
    track = [s for s in spans if s["task"].startswith("track-")]
    model = {s["task"].split("-")[1]: s for s in spans if s["task"].startswith("model-")}
    assert all(s["start"] >= model[s["task"].split("-")[1]]["end"] for s in track)


def test_a_worker_runs_its_libraries_on_one_thread(monkeypatch):
    """The local cluster's worker process starts with OpenMP/BLAS/FFmpeg's decoder at one thread (set before
    numpy loads), and a task keeps OpenCV's pool and every loaded BLAS/OpenMP pool at one thread."""
    from keyshape.batch import ONE_THREAD_ENV, _client
    for k in ONE_THREAD_ENV:                     # not inherited from the test run's settings (conftest)
        monkeypatch.delenv(k, raising=False)

    def pools():
        import os

        import cv2
        from threadpoolctl import threadpool_info

        from keyshape.batch import _one_thread

        env = {k: os.environ.get(k) for k in ONE_THREAD_ENV}
        _one_thread()
        return env, cv2.getNumThreads(), [p["num_threads"] for p in threadpool_info()], os.getpid()

    client, cluster = _client(None, 1, True)
    try:
        env, n_cv, n_pools, pid = client.submit(pools, pure=False).result()
    finally:
        client.close()
        cluster.close()
    assert env == ONE_THREAD_ENV and pid != os.getpid()
    assert n_cv == 1 and n_pools and set(n_pools) == {1}, n_pools


def rep_row(rep, actor, take) -> dict:
    return next(r for r in rep["takes"] if (r["actor"], r["take"]) == (actor, take))


def test_rerun_skips_and_recomputes_only_a_changed_take(library, first_run, tmp_path):
    out0, _ = first_run
    lib = tmp_path / "lib"
    shutil.copytree(library.parent, lib)
    out = tmp_path / "out"
    shutil.copytree(out0, out)
    # the records name the videos by path: the copied library is another path, so hash it once ...
    rep = run_batch(lib / "manifest.toml", out, workers=1, processes=False, show_progress=False)
    assert rep["n_skipped"] == 4 and rep["n_done"] == 0, rep["takes"]
    assert {a["model_status"] for a in rep["actors"].values()} == {"skipped"}
    # ... a touched (same content) video is not recomputed either ...
    os.utime(lib / "actor0" / "take01.mp4")
    rep = run_batch(lib / "manifest.toml", out, workers=1, processes=False, show_progress=False)
    assert rep["n_skipped"] == 4, rep["takes"]
    # ... a changed one is: only that take is tracked again
    before = {p: p.read_bytes() for p in out.rglob("tracks.csv")}
    shutil.copy(lib / "actor0" / "take00.mp4", lib / "actor0" / "take01.mp4")
    rep = run_batch(lib / "manifest.toml", out, workers=1, processes=False, show_progress=False)
    stages = {(r["actor"], r["take"]): r["stages"]["track"] for r in rep["takes"]}
    assert stages == {("actor0", "take00"): "skipped", ("actor0", "take01"): "tracked",
                      ("actor1", "take00"): "skipped", ("actor1", "take01"): "skipped"}, stages
    assert rep["actors"]["actor0"]["keys_status"] == "selected"
    assert rep["actors"]["actor1"]["keys_status"] == "skipped" and rep["actors"]["actor0"]["model_status"] == "skipped"
    changed = [p for p in before if p.read_bytes() != before[p]]
    assert changed == [out / "actor0" / "take01" / "tracks.csv"]
    # the same video now: the same tracks as take00
    assert (out / "actor0" / "take01" / "tracks.csv").read_bytes() == (out / "actor0" / "take00" / "tracks.csv"
                                                                       ).read_bytes()


def test_failing_takes_are_reported_and_the_others_finish(library, first_run, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("keyshape.batch.PROCESSES", False)
    out0, _ = first_run
    lib = library.parent
    (tmp_path / "corrupt.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40)
    labels = tmp_path / "bad_labels"
    shutil.copytree(lib / "actor1" / "footage" / "labels", labels)
    first = sorted(labels.glob("*.pts"))[1]
    lines = first.read_text().splitlines()
    first.write_text("\n".join([lines[0], "n_points: 47", "{"] + lines[3:3 + 47] + ["}"]) + "\n")
    manifest = tmp_path / "m.toml"
    manifest.write_text(f"""
[actors.anna]
model = "{out0 / 'actor0' / 'model.npz'}"
keys = 4
regions = ["mouth", "eyes"]
targets = "{lib / 'actor0' / 'targets'}"
target_regions = "{lib / 'actor0' / 'regions.json'}"

[actors.bob]
video = "{lib / 'actor1' / 'footage' / 'video.mp4'}"
labels = "bad_labels"

[[takes]]
actor = "anna"
video = "{lib / 'actor0' / 'take00.mp4'}"

[[takes]]
actor = "anna"
video = "corrupt.mp4"

[[takes]]
actor = "anna"
video = "{lib / 'actor0' / 'take01.mp4'}"
frames = [10, 25]
name = "part"

[[takes]]
actor = "bob"
video = "{lib / 'actor1' / 'take00.mp4'}"
""")
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "-o", str(out), "--workers", "1", "--quiet"]) == 1
    err = capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    rows = {(r["actor"], r["take"]): r for r in rep["takes"]}
    assert rows[("anna", "take00")]["status"] == "done"
    assert (out / "anna" / "take00" / "weights.csv").is_file()
    part = rows[("anna", "part")]
    assert part["status"] == "done" and part["frames"] == 15, part
    from keyshape.base.formats.tracks import read_tracks
    np.testing.assert_array_equal(read_tracks(out / "anna" / "part" / "tracks.csv").frame, np.arange(10, 25))
    assert (out / "anna" / "part" / "animation.glb").stat().st_size > 0
    bad = rows[("anna", "corrupt")]
    assert bad["status"] == "failed" and "corrupt.mp4" in bad["error"] and "video" in bad["error"], bad
    bob = rows[("bob", "take00")]
    assert bob["status"] == "failed" and f"{first.name}: 47 points, expected 48" in bob["error"], bob
    assert rep["actors"]["bob"]["model_status"] == "failed"
    assert "anna/corrupt failed" in err and "bob/take00 failed" in err
    assert rep["n_failed"] == 2


@pytest.mark.parametrize("text, line, message", [
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\nkeyz = 8\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', 4,
     "unknown key 'keyz' (did you mean 'keys'?)"),
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\nkeys = "8"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', 4,
     "'keys' must be an integer"),
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\n\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n[[takes]]\n'
     'actor = "b"\nvideo = "u.mp4"\n', 9, "unknown actor 'b'"),
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n[[takes]]\n'
     'actor = "a"\nvideo = "x/t.mp4"\n', 7, "already line 4"),
    ('[actors.a]\nvideo = "v.mp4"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', 1, "give labels (with video) or model"),
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\nselector = "best"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', 4,
     "selector 'best'"),
    ('[settings]\noutputs = ["glb", "fbx"]\n[actors.a]\nmodel = "m.npz"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n',
     2, "unknown output 'fbx'"),
    ('[actors.a]\nmodel = "m.npz"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\nframes = [10, 5]\n', 6, "frames must be"),
    ('[actors.a]\nmodel = "m.npz"\n[[takes]]\nactor = "a"\n', 3, "take 1 has no 'video'"),
    ('[actors.a]\nmodel = "m.npz\n', 2, "not valid TOML"),
    ('[actors.a]\nmodel = "m.npz"\n', None, "no takes"),
    ('[actors.a]\nmodel = "m.npz"\ntargets = "t"\nrig = "r"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', 4,
     "give targets (one per key) or a rig, not both"),
    ('[actors.a]\nmodel = "m.npz"\nposes = "p.json"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', 1,
     "poses and landmarks need a rig"),
])
def test_manifest_mistakes_name_file_and_line(tmp_path, text, line, message):
    path = tmp_path / "library.toml"
    path.write_text(text)
    with pytest.raises(InputError) as exc:
        read_manifest(path)
    assert message in str(exc.value)
    assert str(exc.value).startswith(f"{path}, line {line}: " if line else f"{path}: "), str(exc.value)


def test_the_issue_example_works_as_written(tmp_path):
    path = tmp_path / "show.toml"
    path.write_text('[actors.anna]\nvideo = "anna/rom.mp4"        # the footage the labels belong to\n'
                    'labels = "anna/labels"        # .pts folder (or: model = "anna/model.npz")\n\n'
                    '[[takes]]\nactor = "anna"\nvideo = "anna/take01.mp4"\n')
    m = read_manifest(path)
    assert m.actors["anna"].video == tmp_path / "anna" / "rom.mp4" and m.actors["anna"].keys == 8
    assert m.takes[0].name == "take01" and m.takes[0].video == tmp_path / "anna" / "take01.mp4"
    assert m.settings.outputs == ["tracks", "weights", "glb"] and m.settings.solver == "smooth"


def _stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 15
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


@pytest.mark.slow
def test_a_real_scheduler_and_workers_on_localhost(library, first_run, tmp_path):
    """``dask scheduler`` and ``dask worker`` processes on 127.0.0.1 run a batch through ``--scheduler``;
    the results are those of the local cluster's run (the same model file given)."""
    out0, _ = first_run
    lib = library.parent
    sched_file = tmp_path / "scheduler.json"
    log = open(tmp_path / "dask.log", "w")
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = []
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                       "--port", "0", "--no-dashboard", "--scheduler-file", str(sched_file)],
                                      stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path))
        deadline = time.monotonic() + 60
        while not sched_file.is_file() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert sched_file.is_file(), (tmp_path / "dask.log").read_text()
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                                       "--nworkers", "2", "--no-dashboard", "--host", "127.0.0.1",
                                       "--death-timeout", "60", "--local-directory", str(tmp_path / "workers")],
                                      stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path))
        from distributed import Client
        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=90)
        manifest = tmp_path / "m.toml"
        text = (lib / "manifest.toml").read_text()
        text = text.replace('video = "actor0/footage/video.mp4"\nlabels = "actor0/footage/labels"',
                            f'model = "{out0 / "actor0" / "model.npz"}"')
        manifest.write_text(text.replace('"actor', f'"{lib}/actor').replace(f'"{lib}/actor0"', '"actor0"')
                            .replace(f'"{lib}/actor1"', '"actor1"'))
        out = tmp_path / "out"
        assert main(["batch", str(manifest), "-o", str(out), "--scheduler", address, "--quiet"]) == 0
        rep = json.loads((out / "report.json").read_text())
        assert rep["workers"] == 2 and rep["n_done"] == 4 and rep["scheduler"] == address
        assert rep["actors"]["actor0"]["model_status"] == "given"
        assert filecmp.cmp(out / "actor0" / "keys.json", out0 / "actor0" / "keys.json", shallow=False)
        for take in ("take00", "take01"):
            for f in COMPARED:
                assert filecmp.cmp(out / "actor0" / take / f, out0 / "actor0" / take / f, shallow=False), (take, f)
        np.testing.assert_array_equal(json.loads((out / "actor1" / "keys.json").read_text())["regions"]["mouth"]
                                      ["points"], json.loads((out0 / "actor1" / "keys.json").read_text())
                                      ["regions"]["mouth"]["points"])
    finally:
        _stop(procs[::-1])
        log.close()


@pytest.mark.slow
def test_ctrl_c_leaves_only_complete_outputs_and_a_rerun_finishes(library, tmp_path):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) once the first take is done:
    status 130, no temporary files, every file there complete; the rerun skips what was finished."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", "batch", str(library), "-o", str(out), "--workers", "2"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, start_new_session=True,
                            preexec_fn=sigint_as_a_terminal_gives_it)
    try:
        deadline = time.monotonic() + 240
        for line in proc.stderr:
            if "1/4 takes" in line or time.monotonic() > deadline:
                break
        os.killpg(proc.pid, signal.SIGINT)
        err = proc.stderr.read()
        assert proc.wait(timeout=60) == 130, err
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stderr.close()
    assert "interrupted" in err
    assert not [p for p in out.rglob("*") if ".partial" in p.name]
    assert not (out / "report.json").exists()
    from keyshape.base.formats.tracks import read_tracks
    done = list(out.rglob("tracks.csv"))
    assert done, "the first take's outputs should be there"
    for p in done:
        assert read_tracks(p).n_frames == FRAMES
    rep = run_batch(library, out, workers=1, processes=False, show_progress=False)
    assert rep["n_failed"] == 0 and rep["n_skipped"] + rep["n_done"] == 4
    assert any(r["stages"]["track"] == "skipped" for r in rep["takes"])
