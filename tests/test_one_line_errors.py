"""Bad options and request bodies that used to end in a traceback (issue 27): each is exit 2 with one
line naming the option, before any work, and nothing is written."""
from __future__ import annotations

import pytest

from keyshape.cli import main


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err and "\n" not in err and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("argv", [
    ["synth", "mocap", "out"],
    ["synth", "video", "out"],
])
@pytest.mark.parametrize("seed", ["-1", "4294967296", "99999999999999999999"])
def test_a_seed_out_of_range_is_one_line(tmp_path, capsys, monkeypatch, argv, seed):
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--seed", seed]) == 2
    assert f"--seed {seed}" in one_line(capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    ["pose-edit", "poses.json", "--rig", "no_such_rig"],            # checked before the rig is loaded
    ["label", "v.mp4", "-o", "lab", "--serve"],
])
@pytest.mark.parametrize("port", ["99999", "-1", "65536"])
def test_a_port_out_of_range_is_one_line(tmp_path, capsys, monkeypatch, argv, port):
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--port", port]) == 2
    assert f"--port {port}" in one_line(capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("option, value", [("--size", "0"), ("--size", "-3"), ("--size", "99999")])
def test_preview_options_out_of_range_are_one_line(tmp_path, capsys, option, value):
    argv = ["preview", "v.mp4", "--tracks", "t.csv", "--curves", "c.csv", "--rig", "rig",
            "--sheet", str(tmp_path / "s.jpg"), option, value]
    assert main(argv) == 2
    assert option in one_line(capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("body", [
    b'{"pose": {"jawOpen": 1' + b"0" * 400 + b"}}",                   # beyond the float range
    b'{"pose": {"jawOpen": 1' + b"0" * 5000 + b"}}",                  # beyond Python's int parsing limit
    b'{"pose": {"jawOpen": -1' + b"0" * 400 + b"}}",
    b'{"pose": {"jawOpen": 1e999}}',
])
def test_a_huge_number_in_a_pose_edit_request_is_a_4xx(tmp_path, body):
    from server_helpers import request, serving
    from test_pose_edit import pose_page_server
    with serving(pose_page_server(tmp_path)) as server:
        before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
        status, reply = request(server, "PUT", "/api/poses/mouth_0", body)
        assert status == 400, reply
        assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
        assert request(server, "GET", "/api/library")[0] == 200        # the server still answers


# --------------------------------------------------------------------------- late or misleading messages
@pytest.fixture(scope="module")
def take(tmp_path_factory):
    d = tmp_path_factory.mktemp("msg")
    assert main(["synth", "video", str(d / "foot"), "--frames", "12", "--size", "160x120", "--labels", "2"]) == 0
    return d / "foot"


def test_a_byte_order_mark_is_not_a_column(take, tmp_path):
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.weights import read_weights
    t = tmp_path / "bom.csv"
    t.write_bytes(b"\xef\xbb\xbf" + (take / "truth.csv").read_bytes())
    assert read_tracks(t).n_frames == 12
    w = tmp_path / "w.csv"
    w.write_bytes(b"\xef\xbb\xbfframe,mouth_0\n0,0.5\n1,0.25\n")
    assert read_weights(w).names == ["mouth_0"]


def test_an_extra_column_is_named(take, tmp_path, capsys):
    lines = [ln for ln in (take / "truth.csv").read_text().splitlines() if not ln.startswith("#")]
    t = tmp_path / "extra.csv"
    t.write_text("\n".join([lines[0] + ",notes"] + [ln + ",1" for ln in lines[1:]]) + "\n")
    assert main(["select", str(t), "-k", "2", "-o", str(tmp_path / "k.json")]) == 2
    assert "extra column(s) ['notes']" in one_line(capsys)


def test_a_folder_where_a_file_is_expected_says_so(tmp_path, capsys):
    (tmp_path / "x.mp4").mkdir()
    (tmp_path / "m.npz").mkdir()
    assert main(["track", str(tmp_path / "x.mp4"), "--model", str(tmp_path / "m.npz"), "-o",
                 str(tmp_path / "t.csv")]) == 2
    err = one_line(capsys)
    assert "is a folder" in err and "not found" not in err


def test_a_file_name_too_long_is_refused_before_work_naming_it(take, tmp_path, capsys):
    out = tmp_path / ("k" * 250 + ".json")
    assert main(["select", str(take / "truth.csv"), "-k", "2", "-o", str(out)]) == 2
    err = one_line(capsys)
    assert "too long" in err and "k" * 250 in err
    assert list(tmp_path.iterdir()) == []


def test_write_errors_name_the_users_file_not_the_temporary_one(tmp_path, monkeypatch):
    import errno
    import os

    from keyshape.base.files import atomic_path, atomic_write, describe_os_error
    out = tmp_path / "out.csv"
    out.write_text("earlier")

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError) as exc:
        with atomic_write(out) as f:
            f.write("new")
    monkeypatch.undo()
    msg = describe_os_error(exc.value)
    assert msg.startswith(str(out)) and "disk full" in msg and ".partial" not in msg
    with pytest.raises(OSError) as exc:                     # a writer that opens the temporary file itself
        with atomic_path(out) as tmp:
            raise OSError(errno.EROFS, "Read-only file system", str(tmp))
    assert str(exc.value.filename) == str(out)
    with pytest.raises(OSError) as exc:                     # another file's error stays that file's
        with atomic_path(out) as tmp:
            raise OSError(errno.ENOENT, "No such file", str(tmp_path / "input.csv"))
    assert str(exc.value.filename) == str(tmp_path / "input.csv")
    assert out.read_text() == "earlier" and sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]
