"""``keyshape batch`` never writes over what it did not write, refuses names that collide with its own
layout or an input before any work, redoes damaged outputs instead of reusing them, warns of short
takes, and turns every bad manifest value or option into one line (issue 27)."""
from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from keyshape.base.errors import InputError
from keyshape.batch import _short_take, run_batch
from keyshape.cli import main
from keyshape.manifest import Take, read_manifest


def tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """One actor, one take of 30 frames, run once: (library folder, its first output folder)."""
    from synth_library import synth_library

    lib = synth_library(tmp_path_factory.mktemp("lib"), actors=1, takes=1, frames=30, keys=3, morphs=20,
                        size=(320, 240), labels=8)
    out = lib.parent / "out"
    rep = run_batch(lib, out, workers=1, processes=False, show_progress=False)
    assert rep["n_done"] == 1, rep
    return lib


# --------------------------------------------------------------------------- never over a user's file
@pytest.mark.parametrize("user_file", ["report.json", "actor0/keys.json", "actor0/model.npz", "actor0/batch.json",
                                       "actor0/take00/weights.csv", "actor0/take00/animation.glb",
                                       "actor0/take00/tracks.csv"])
def test_a_users_file_where_batch_writes_is_refused_before_work(small, tmp_path, user_file):
    out = tmp_path / "out"
    (out / user_file).parent.mkdir(parents=True)
    (out / user_file).write_text("the user's own")
    before = tree(out)
    with pytest.raises(InputError, match="not written by keyshape batch") as exc:
        run_batch(small, out, workers=1, processes=False, show_progress=False)
    assert "\n" not in str(exc.value) and user_file.split("/")[-1] in str(exc.value)
    assert tree(out) == before


def test_batch_outputs_into_the_library_folder_keep_the_library(small, tmp_path):
    lib = tmp_path / "lib"
    shutil.copytree(small.parent, lib, ignore=shutil.ignore_patterns("out"))
    before = tree(lib)
    rep = run_batch(lib / "manifest.toml", lib, workers=1, processes=False, show_progress=False)  # -o .
    assert rep["n_done"] == 1, rep
    after = tree(lib)
    assert all(after.get(k) == v for k, v in before.items())


def _manifest(tmp_path: Path, take_name: str | None = None, labels: str = "anna/labels") -> Path:
    (tmp_path / "anna" / "labels").mkdir(parents=True, exist_ok=True)
    (tmp_path / "anna" / "labels" / "000001.pts").write_text("the user's labels")
    (tmp_path / "anna" / "rom.mp4").write_bytes(b"")
    m = tmp_path / "show.toml"
    name = f'name = "{take_name}"\n' if take_name else ""
    m.write_text(f'[actors.anna]\nvideo = "anna/rom.mp4"\nlabels = "{labels}"\n\n'
                 f'[[takes]]\nactor = "anna"\nvideo = "anna/take01.mp4"\n{name}')
    return m


def test_a_take_named_like_an_input_folder_is_refused_before_work(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("keyshape.batch.PROCESSES", False)
    m = _manifest(tmp_path, "labels")
    before = tree(tmp_path)
    assert main(["batch", str(m), "-o", str(tmp_path), "--workers", "1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "take 'labels'" in err and "input" in err and "\n" not in err
    assert tree(tmp_path) == before


@pytest.mark.parametrize("name", ["keys.json", "model.npz", "batch.json"])
def test_a_take_named_like_a_batch_file_is_refused_by_the_manifest_check(tmp_path, name):
    with pytest.raises(InputError, match="a file keyshape batch writes"):
        read_manifest(_manifest(tmp_path, name))


# --------------------------------------------------------------------------- reused outputs are checked
def test_damaged_outputs_are_redone_not_skipped(small, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(small.parent / "out", out)
    good = tree(out)
    take = out / "actor0" / "take00"
    w = (take / "weights.csv").read_bytes()
    (take / "weights.csv").write_bytes(w[: len(w) // 2])               # truncated
    (take / "animation.glb").write_bytes(b"")                          # emptied
    rep = run_batch(small, out, workers=1, processes=False, show_progress=False)
    row = rep["takes"][0]
    assert row["status"] == "done" and row["stages"]["finish"] == "done", row
    after = tree(out)
    for name in ("weights.csv", "animation.glb"):
        k = f"actor0/take00/{name}"
        assert after[k] == good[k]
    rep = run_batch(small, out, workers=1, processes=False, show_progress=False)
    assert rep["takes"][0]["status"] == "skipped"


def test_a_short_take_is_warned_of(small):
    video = small.parent / "actor0" / "take00.mp4"
    take = Take("actor0", video, "take00")
    assert _short_take(take, 30) == {}
    w = _short_take(take, 15)["warning"]
    assert "ended after 15 of the 30 frames" in w and "take00.mp4" in w
    assert _short_take(Take("actor0", video, "t", 10, 20), 10) == {}
    assert "ended after 5 of the 10" in _short_take(Take("actor0", video, "t", 10, 20), 5)["warning"]


# --------------------------------------------------------------------------- one line before any work
@pytest.mark.parametrize("body, message", [
    ('[actors.a]\nmodel = "m.npz"\ntakes = 1\n', "unknown key"),
    ('takes = ["a.mp4"]\n[actors.a]\nmodel = "m.npz"\n', "each take must be a table"),
    ('[settings]\nridge = nan\n[actors.a]\nmodel = "m.npz"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', "ridge"),
    ('[settings]\nsmooth_lambda = inf\n[actors.a]\nmodel = "m.npz"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n',
     "smooth_lambda"),
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\ncomponents = 0\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n',
     "components = 0"),
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\nmorphs = -5\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n',
     "morphs = -5"),
    ('[actors.a]\nvideo = "v.mp4"\nlabels = "l"\nseed = -1\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n', "seed = -1"),
    ('[actors."report.json"]\nmodel = "m.npz"\n[[takes]]\nactor = "report.json"\nvideo = "t.mp4"\n',
     "a file keyshape batch writes"),
    ('[settings]\noutputs = [1]\n[actors.a]\nmodel = "m.npz"\n[[takes]]\nactor = "a"\nvideo = "t.mp4"\n',
     "unknown output 1"),
])
def test_bad_manifest_values_are_one_line(tmp_path, capsys, body, message):
    m = tmp_path / "show.toml"
    m.write_text(body)
    assert main(["batch", str(m), "-o", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and str(m) in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("scheduler", ["garbage::://", "tcp://", "http://x:1", "tcp://127.0.0.1:99999"])
def test_a_bad_scheduler_is_one_line_and_creates_nothing(small, tmp_path, capsys, scheduler):
    out = tmp_path / "out"
    assert main(["batch", str(small), "-o", str(out), "--scheduler", scheduler, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--scheduler" in err and "\n" not in err, err
    assert not out.exists()


def test_an_unreachable_scheduler_is_one_line_and_creates_nothing(small, tmp_path, capsys, monkeypatch):
    import socket

    import keyshape.batch
    monkeypatch.setattr(keyshape.batch, "CONNECT_TIMEOUT", "1s")   # the same refusal, without 20 s of retries
    with socket.socket() as s:                                   # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "out"
    assert main(["batch", str(small), "-o", str(out), "--scheduler", f"tcp://127.0.0.1:{port}", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "cannot connect" in err and "\n" not in err, err
    assert not out.exists()


# --------------------------------------------------------------------------- user edits survive a rerun (issue 37)
def test_a_rerun_keeps_edited_keys_and_tracks_and_says_which(small, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(small.parent / "out", out)
    for rel in ("actor0/keys.json", "actor0/take00/tracks.csv"):
        p = out / rel
        original = p.read_bytes()
        p.write_bytes(original + b"\n")                               # the user's edit
        before = tree(out)
        with pytest.raises(InputError, match="changed since keyshape batch wrote it") as exc:
            run_batch(small, out, workers=1, processes=False, show_progress=False)
        assert p.name in str(exc.value) and "delete" in str(exc.value) and "\n" not in str(exc.value)
        assert tree(out) == before
        p.write_bytes(original)


def test_remove_partials_deletes_only_this_runs_temporaries(small, tmp_path):
    from keyshape.batch import remove_partials
    m = read_manifest(small)
    out = tmp_path / "out"
    take = out / "actor0" / "take00"
    take.mkdir(parents=True)
    mine = [take / ".notes.v2.partial.txt", take / ".draft.abc.partial", out / ".x.y.partial.csv"]
    for p in mine:
        p.write_text("the user's")
    ours = take / ".weights.csv.ksdeadbeef-abc123.partial.csv"
    ours.write_text("temporary")
    assert remove_partials(out, m, token="ksdeadbeef") == 1
    assert not ours.exists() and all(p.read_text() == "the user's" for p in mine)
