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
    ["train", "v.mp4", "--labels", "l", "-o", "m.npz"],
    ["select", "t.csv", "-o", "k.json"],
    ["compare", "t.csv", "-o", "out"],
    ["synth", "mocap", "out"],
    ["synth", "video", "out"],
    ["keypoints", "s.npz", "--initial", "4", "-o", "k.json"],
    ["transfer", "s.npz", "--target", "t.obj", "-o", "o.npz"],
    ["demo", "out"],
    ["label", "v.mp4", "-o", "lab"],
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


@pytest.mark.parametrize("option, value", [("--sheet-frames", "0"), ("--sheet-frames", "-3"), ("--size", "0")])
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
