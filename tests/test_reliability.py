"""Outputs that never destroy data, inputs checked for sense, every failure a one-line error.

Table-driven command-line cases (issue 17): each asserts the exit status, a phrase of the one-line
message, and that no file was created or changed. Then interruption tests that send SIGINT and
SIGTERM to real ``keyshape`` subprocesses and check that earlier outputs survive.
"""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import sigint_as_a_terminal_gives_it

from keyshape.base.errors import InputError
from keyshape.base.files import MANIFEST, atomic_dir, check_output, check_outputs
from keyshape.base.formats.obj import Mesh, write_obj
from keyshape.cli import main


def snapshot(root: Path) -> dict:
    """Every file under ``root`` (hidden ones included) with its bytes and modification time."""
    return {str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A tiny synthetic take run through synth -> select -> decompose, plus OBJ targets and meshes."""
    d = tmp_path_factory.mktemp("rel")
    assert main(["synth", "video", str(d / "foot"), "--frames", "24", "--size", "160x120", "--labels", "4"]) == 0
    tracks = d / "foot" / "truth.csv"
    assert main(["select", str(tracks), "-k", "2", "--region", "mouth", "-o", str(d / "keys.json")]) == 0
    assert main(["decompose", str(tracks), "--keys", str(d / "keys.json"), "-o", str(d / "w.csv")]) == 0
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    m = Mesh(v, [np.array([0, 1, 2]), np.array([0, 2, 3]), np.array([1, 4, 5]), np.array([1, 5, 2])])
    t = d / "targets"
    t.mkdir()
    write_obj(t / "neutral.obj", m)
    rng = np.random.default_rng(0)
    for c in ("mouth_0", "mouth_1"):
        write_obj(t / f"{c}.obj", m, v + rng.normal(scale=0.1, size=v.shape))
    return d


def _weights_text(work) -> str:
    return (work / "w.csv").read_text()


def _write(path: Path, text: str | bytes) -> Path:
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
    return path


# --------------------------------------------------------------------------- table of bad runs
def _cases(work: Path, tmp: Path):
    """(name, argv, phrase expected in the error). Paths under ``tmp`` must stay unchanged."""
    tracks = str(work / "foot" / "truth.csv")
    video = str(work / "foot" / "video.mp4")
    keys = str(work / "keys.json")
    w = str(work / "w.csv")
    targets = str(work / "targets")
    lines = (work / "foot" / "truth.csv").read_text().splitlines()
    header, rows = lines[0], lines[1:]
    big = rows[3].split(",")
    big[5] = "1e300"
    shuffled = [header] + [rows[1], rows[0]] + rows[2:]
    gapped = [header] + rows[:5] + rows[8:]
    short = tmp / "short.mp4"
    from keyshape.base.formats.video import VideoReader, video_writer
    frames = VideoReader(video).read_frames([0, 1, 2])
    with video_writer(short, 30, (frames.shape[2], frames.shape[1])) as vw:
        for f in frames:
            vw.write(f)
    wl = _weights_text(work).splitlines()
    bad_w = wl[:]
    col = 2 if wl[0].split(",")[1] == "time" else 1              # the first weight column
    cells = bad_w[2].split(",")
    bad_w[2] = ",".join(cells[:col] + ["1e300"] + cells[col + 1:])
    (tmp / "file").write_text("a file, not a folder")
    case_dir = tmp / "casedir"
    case_dir.mkdir()
    import shutil
    for f in Path(targets).iterdir():
        shutil.copy(f, case_dir / f.name)
    shutil.copy(case_dir / "mouth_1.obj", case_dir / "MOUTH_1.obj")
    mine = tmp / "mine"
    mine.mkdir()
    (mine / "artist_notes.txt").write_text("precious")
    return [
        ("sheet gif", ["select", tracks, "-k", "2", "-o", str(tmp / "k.json"), "--sheet", str(tmp / "x.gif"),
                       "--video", video], "use a .png or .jpg"),
        ("video too short", ["select", tracks, "-k", "2", "-o", str(tmp / "k.json"), "--sheet",
                             str(tmp / "s.png"), "--video", str(short)], "video has 3 frames"),
        ("output under a file", ["decompose", tracks, "--keys", keys, "-o", str(tmp / "file" / "w.csv")],
         "is not a folder"),
        ("output is a folder", ["decompose", tracks, "--keys", keys, "-o", str(tmp)], "is a folder"),
        ("output is an input", ["decompose", tracks, "--keys", keys, "-o", tracks], "one of the inputs"),
        ("tracks 1e300", ["select", _write(tmp / "big.csv", "\n".join([header, *rows[:3], ",".join(big),
                                                                        *rows[4:]]) + "\n").as_posix(),
                          "-k", "2", "-o", str(tmp / "k.json")], "implausible"),
        ("tracks shuffled", ["select", _write(tmp / "shuf.csv", "\n".join(shuffled) + "\n").as_posix(), "-k", "2",
                             "-o", str(tmp / "k.json")], "unique and increasing"),
        ("tracks gapped", ["select", _write(tmp / "gap.csv", "\n".join(gapped) + "\n").as_posix(), "-k", "2",
                           "-o", str(tmp / "k.json")], "frame numbers jump from 4 to 8"),
        ("partial tracks", ["select", _write(tmp / "t.partial.csv", "# keyshape partial tracks: interrupted\n"
                                             + "\n".join(lines) + "\n").as_posix(), "-k", "2",
                            "-o", str(tmp / "k.json")], "--accept-partial"),
        ("weights 1e300", ["retarget", _write(tmp / "w300.csv", "\n".join(bad_w) + "\n").as_posix(),
                           "--targets", targets, "-o", str(tmp / "a.glb")], "implausible weight"),
        ("weights not UTF-8", ["retarget", _write(tmp / "wbin.csv", b"frame,mouth_0\n0,\xff\xfe\n").as_posix(),
                               "--targets", targets, "-o", str(tmp / "a.glb")], "not a UTF-8"),
        ("targets differ by case", ["retarget", w, "--targets", str(case_dir), "-o", str(tmp / "a.glb")],
         "differ only by case"),
        ("retarget into a folder keyshape did not make", ["retarget", w, "--targets", targets, "-o", str(mine)],
         "--overwrite"),
        ("retarget into the targets folder", ["retarget", w, "--targets", targets, "-o", targets],
         "input folder"),
        ("compare into a folder keyshape did not make", ["compare", tracks, "--kmax", "3", "-o", str(mine)],
         "not made by keyshape"),
        ("rigid a,a,a", ["mocap", "x.c3d", "--target", "t.obj", "--target-markers", "m.json", "--rigid", "a,a,a",
                         "-o", str(tmp / "o.npz")], "more than once"),
        ("rigid @missing", ["mocap", "x.c3d", "--target", "t.obj", "--target-markers", "m.json",
                            "--rigid", "@" + str(tmp / "missing.txt"), "-o", str(tmp / "o.npz")], "not found"),
    ]


def test_bad_runs_fail_with_one_line_and_change_nothing(work, tmp_path, capsys):
    cases = _cases(work, tmp_path)
    before_work = snapshot(work)
    failures = []
    for name, argv, phrase in cases:
        before = snapshot(tmp_path)
        capsys.readouterr()
        rc = main([str(a) for a in argv])
        err = capsys.readouterr().err.strip()
        after = snapshot(tmp_path)
        if rc != 2 or phrase not in err or "\n" in err or "Traceback" in err or after != before:
            failures.append(f"{name}: rc={rc}, err={err!r}, changed={sorted(set(after) ^ set(before))}")
    assert snapshot(work) == before_work, "an input was changed"
    assert not failures, "\n".join(failures)


def test_partial_tracks_accepted_when_asked(work, tmp_path):
    lines = (work / "foot" / "truth.csv").read_text()
    part = _write(tmp_path / "t.partial.csv", "# keyshape partial tracks: interrupted after 24 frames\n" + lines)
    assert main(["select", str(part), "-k", "2", "--region", "mouth", "--accept-partial",
                 "-o", str(tmp_path / "k.json")]) == 0


def test_register_writes_nothing_when_markers_are_bad(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("keyshape.retarget.dense.cli.CONTROLS", 10)
    from tests.test_dense import grid   # noqa: PLC0415 - the test meshes of test_dense
    v, t = grid(6)
    write_obj(tmp_path / "ref.obj", Mesh(v, list(t)))
    write_obj(tmp_path / "tgt.obj", Mesh(v + 0.01, list(t)))
    (tmp_path / "pairs.json").write_text(json.dumps([{"reference": i, "target": i} for i in (0, 5, 30, 35, 14)]))
    (tmp_path / "m.json").write_text(json.dumps({"tip": 10 ** 6}))
    (tmp_path / "one.json").write_text(json.dumps([{"reference": i, "target": 0} for i in (0, 5, 30, 35)]))
    before = snapshot(tmp_path)
    rc = main(["register", str(tmp_path / "ref.obj"), str(tmp_path / "tgt.obj"), "--landmarks",
               str(tmp_path / "pairs.json"), "-o", str(tmp_path / "fit.obj"),
               "--markers", str(tmp_path / "m.json"), "--out-markers", str(tmp_path / "tm.json")])
    assert rc == 2 and "vertex 1000000 does not exist" in capsys.readouterr().err
    rc = main(["register", str(tmp_path / "ref.obj"), str(tmp_path / "tgt.obj"), "--landmarks",
               str(tmp_path / "one.json"), "-o", str(tmp_path / "fit.obj")])
    assert rc == 2 and "on one point" in capsys.readouterr().err
    assert snapshot(tmp_path) == before


def test_disk_full_is_one_line_and_leaves_no_temporary(work, tmp_path, monkeypatch, capsys):
    import keyshape.base.files as files

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(files.os, "fsync", full)
    out = tmp_path / "w.csv"
    out.write_text("earlier")                   # the user's own file: replaced only with --overwrite
    rc = main(["decompose", str(work / "foot" / "truth.csv"), "--keys", str(work / "keys.json"), "-o", str(out),
               "--overwrite"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "disk full" in err and "\n" not in err
    assert out.read_text() == "earlier" and sorted(p.name for p in tmp_path.iterdir()) == ["w.csv"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into read-only folders")
def test_read_only_folder_is_refused_before_work(work, tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        rc = main(["decompose", str(work / "foot" / "truth.csv"), "--keys", str(work / "keys.json"),
                   "-o", str(ro / "w.csv")])
        assert rc == 2 and "not writable" in capsys.readouterr().err
    finally:
        ro.chmod(0o755)


def test_collapsed_labels_and_duplicate_label_files_are_refused(work, tmp_path, capsys):
    import shutil
    labels = tmp_path / "labels"
    shutil.copytree(work / "foot" / "labels", labels)
    first = sorted(labels.glob("*.pts"))[0]
    frame = int(first.stem)
    shutil.copy(first, labels / f"{frame}.pts")                  # 35.pts beside 000035.pts
    video = str(work / "foot" / "video.mp4")
    assert main(["train", video, "--labels", str(labels), "-o", str(tmp_path / "m.npz")]) == 2
    assert f"two label files for frame {frame}" in capsys.readouterr().err
    (labels / f"{frame}.pts").unlink()
    from keyshape.base.formats.labels import read_pts, write_pts
    write_pts(first, np.full_like(read_pts(first), 50.0))        # every point on one spot
    assert main(["train", video, "--labels", str(labels), "-o", str(tmp_path / "m.npz")]) == 2
    assert "collapsed onto one spot" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()


# --------------------------------------------------------------------------- folder outputs
def test_folder_output_writes_only_its_files(work, tmp_path, capsys):
    w, targets = str(work / "w.csv"), str(work / "targets")
    out = tmp_path / "frames"
    assert main(["retarget", w, "--targets", targets, "-o", str(out)]) == 0
    n = len(list(out.glob("frame_*.obj")))
    assert n == 24 and (out / MANIFEST).is_file()
    (out / "notes.txt").write_text("mine")                       # a user's file beside keyshape's
    assert main(["retarget", w, "--targets", targets, "-o", str(out)]) == 0     # keyshape's folder: no flag
    assert (out / "notes.txt").read_text() == "mine" and len(list(out.glob("frame_*.obj"))) == n
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "keep.txt").write_text("keep")
    assert main(["retarget", w, "--targets", targets, "-o", str(mine), "--overwrite"]) == 0
    assert (mine / "keep.txt").read_text() == "keep" and len(list(mine.glob("frame_*.obj"))) == n
    assert not [p for p in tmp_path.rglob(".keyshape-*") if p.name != MANIFEST]


def test_output_dot_works(work, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["retarget", str(work / "w.csv"), "--targets", str(work / "targets"), "-o", "."]) == 0
    assert len(list(tmp_path.glob("frame_*.obj"))) == 24
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [MANIFEST]


def test_atomic_dir_prunes_only_its_own_earlier_files(tmp_path):
    out = tmp_path / "o"
    with atomic_dir(out) as d:
        (d / "a").write_text("1")
        (d / "b").write_text("1")
    (out / "user").write_text("u")
    with atomic_dir(out) as d:
        (d / "a").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "a", "user"]
    with pytest.raises(KeyboardInterrupt):
        with atomic_dir(out) as d:
            (d / "a").write_text("3")
            raise KeyboardInterrupt
    assert (out / "a").read_text() == "2" and sorted(p.name for p in out.iterdir()) == [MANIFEST, "a", "user"]
    with pytest.raises(InputError, match="would overwrite its input"):
        with atomic_dir(out, inputs=[out / "user"], overwrite=True) as d:
            (d / "user").write_text("x")
    assert (out / "user").read_text() == "u"


def test_check_outputs(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="is not a folder"):
        check_output(tmp_path / "f" / "o.csv")
    with pytest.raises(InputError, match="is a folder"):
        check_output(tmp_path)
    with pytest.raises(InputError, match="one of the inputs"):
        check_outputs([tmp_path / "f"], inputs=[tmp_path / "f"])
    with pytest.raises(InputError, match="named twice"):
        check_outputs([tmp_path / "a.csv", tmp_path / "a.csv"])
    check_output(tmp_path / "new" / "deeper" / "o.csv")          # missing parents are made when writing


# --------------------------------------------------------------------------- interruption (real processes)
def _keyshape(*args, **kw) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "keyshape", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, preexec_fn=sigint_as_a_terminal_gives_it,
                            **kw)


def _finish(proc: subprocess.Popen, timeout: float) -> tuple[str, str]:
    """``proc.communicate(timeout)``; a process still running then is killed and reaped (its pipes
    closed) before the failure is raised, so that it does not spill into later tests' warnings."""
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"still running {timeout:g} s after the signal; stderr: {err[-1500:]}") from None


def _wait_for(cond, proc, timeout=120.0) -> None:
    t0 = time.monotonic()
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"finished before the signal: {proc.communicate()}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            raise AssertionError("timed out waiting")
        time.sleep(0.005)


@pytest.fixture(scope="module")
def long_take(tmp_path_factory):
    """A 400-frame video and a model trained on it (tracking it takes a few seconds)."""
    d = tmp_path_factory.mktemp("long")
    assert main(["synth", "video", str(d / "foot"), "--frames", "400", "--size", "200x150", "--labels", "6"]) == 0
    assert main(["train", str(d / "foot" / "video.mp4"), "--labels", str(d / "foot" / "labels"), "--morphs", "10",
                 "-o", str(d / "model.npz")]) == 0
    return d


@pytest.mark.parametrize("sig, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupted_track_keeps_the_earlier_tracks(long_take, tmp_path, sig, status):
    out = tmp_path / "tracks.csv"
    out.write_text("earlier complete tracks\n")              # the user's own: replaced only with --overwrite
    proc = _keyshape("track", long_take / "foot" / "video.mp4", "--model", long_take / "model.npz", "-o", out,
                     "--quiet", "--overwrite", cwd=tmp_path)

    def rows_written():
        tmp = [p for p in tmp_path.glob(".tracks.csv.*.partial")]
        return bool(tmp) and tmp[0].stat().st_size > 2000

    _wait_for(rows_written, proc)
    proc.send_signal(sig)
    stdout, stderr = _finish(proc, 60)
    assert proc.returncode == status, stderr
    assert out.read_text() == "earlier complete tracks\n"
    part = tmp_path / "tracks.partial.csv"
    assert part.read_text().startswith("# keyshape partial tracks: interrupted after")
    assert "interrupted" in stdout and "Traceback" not in stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST, "tracks.csv", "tracks.partial.csv"]  # no temporaries


@pytest.mark.parametrize("sig, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupted_retarget_keeps_the_earlier_frames(work, tmp_path, sig, status):
    from keyshape.base.formats.weights import read_weights, write_weights
    fr, names, w, _ = read_weights(work / "w.csv")
    n = 3000
    write_weights(tmp_path / "long.csv", np.arange(n), names, np.resize(w, (n, w.shape[1])))
    out = tmp_path / "frames"
    assert main(["retarget", str(work / "w.csv"), "--targets", str(work / "targets"), "-o", str(out)]) == 0
    before = snapshot(out)
    proc = _keyshape("retarget", tmp_path / "long.csv", "--targets", work / "targets", "-o", out)
    _wait_for(lambda: any(out.glob(".keyshape-*.partial/*")), proc)
    proc.send_signal(sig)
    stdout, stderr = _finish(proc, 60)
    assert proc.returncode == status, stderr
    assert "interrupted" in stderr or "terminated" in stderr
    assert snapshot(out) == before


def test_interrupted_demo_exits_130_and_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "old_result.txt").write_text("old")
    proc = _keyshape("demo", out, "--frames", "60", "--overwrite")
    _wait_for(lambda: any(out.glob(".keyshape-*.partial/footage/video.mp4")), proc, timeout=300)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = _finish(proc, 120)
    assert proc.returncode == 130, stderr
    assert sorted(p.name for p in out.iterdir()) == ["old_result.txt"]


def test_target_markers_far_or_collapsed_are_refused(tmp_path):
    from keyshape.retarget.mocap.cli import read_target_markers
    v = np.random.default_rng(0).uniform(0, 10, (50, 3))
    (tmp_path / "far.json").write_text(json.dumps({"a": 3, "b": [5.0, 5.0, 1e6]}))
    with pytest.raises(InputError, match="outside the target mesh"):
        read_target_markers(tmp_path / "far.json", len(v), v)
    (tmp_path / "one.json").write_text(json.dumps({f"m{i}": [1.0, 2.0, 3.0] for i in range(28)}))
    with pytest.raises(InputError, match="28 target markers on one point"):
        read_target_markers(tmp_path / "one.json", len(v), v)
    (tmp_path / "ok.json").write_text(json.dumps({"a": 3, "b": [5.0, 5.0, 5.0], "c": 7}))
    assert sorted(read_target_markers(tmp_path / "ok.json", len(v), v)) == ["a", "b", "c"]


def test_a_rig_edited_in_place_keeping_size_and_time_is_read_again(tmp_path, monkeypatch):
    """issue 37: the rig cache is keyed by content; an edit that keeps the file's size and modification
    time (as ``cp -p``, ``rsync -a`` or tar leave it) is not served from the stale cache."""
    from test_rig_poses import write_toy_rig

    from keyshape.retarget.rig.model import load_rig
    monkeypatch.setenv("KEYSHAPE_CACHE", str(tmp_path / "cache"))
    rig, _ = write_toy_rig(tmp_path / "rig")
    first = load_rig(rig)
    shape = sorted(p for p in rig.glob("*.obj") if p.name != "neutral.obj")[0]
    st = os.stat(shape)
    lines = shape.read_text().splitlines(keepends=True)
    i = next(k for k, line in enumerate(lines) if line.startswith("v "))
    x = lines[i].split()
    x[1] = x[1][:-1] + ("1" if x[1][-1] != "1" else "2")        # same length: one digit changed
    lines[i] = " ".join(x) + "\n"
    shape.write_text("".join(lines))
    os.utime(shape, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(shape).st_size == st.st_size and os.stat(shape).st_mtime_ns == st.st_mtime_ns
    second = load_rig(rig)
    k = first.names.index(shape.stem)
    assert not np.array_equal(first.deltas[k], second.deltas[k])
