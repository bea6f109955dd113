"""Pose-correction page (keyshape pose-edit): serves the library, renders poses, writes only POSES.json."""
from __future__ import annotations

import json

import numpy as np
import pytest

from keyshape.base.formats.keys import write_keys
from keyshape.base.formats.poses import read_poses
from keyshape.cli import main
from keyshape.retarget.rig.pose_edit import PoseServer, check_pose
from keyshape.retarget.rig.model import load_rig
from server_helpers import request, serving
from test_rig_poses import SHAPES, TRUE, actor_keys, write_toy_rig


def pose_page_server(tmp_path) -> PoseServer:
    """A pose page (not yet serving) on the toy rig's POSES.json, written by ``keyshape pose``."""
    rig, lm = write_toy_rig(tmp_path / "rig")
    write_keys(tmp_path / "keys.json", "contours48", 48, actor_keys(TRUE))
    assert main(["pose", str(tmp_path / "keys.json"), "--rig", str(rig), "--landmarks", str(lm),
                 "-o", str(tmp_path / "poses.json")]) == 0
    return PoseServer(tmp_path / "poses.json", load_rig(rig), port=0, size=96)


@pytest.fixture
def running(tmp_path):
    with serving(pose_page_server(tmp_path)) as server:
        yield server, tmp_path


def test_page_and_library_are_served_with_the_actor_keys(running):
    server, _ = running
    status, body = request(server, "GET", "/")
    assert status == 200 and b"app.js" in body
    assert request(server, "GET", "/app.js")[0] == 200
    status, body = request(server, "GET", "/api/library")
    lib = json.loads(body)
    assert status == 200 and lib["range"] == [0.0, 1.0]
    assert lib["regions"]["mouth"]["keys"]["mouth_0"]["jawOpen"] == pytest.approx(0.7, abs=0.03)
    a = lib["actor"]["mouth_0"]                       # KEYS.json found through POSES.json's keys.file
    assert len(a["shape"]) == len(a["rest"]) == 20 and a["lines"] and len(a["closed"]) == len(a["lines"])


def test_a_corrected_pose_is_saved_and_rendered(running):
    import cv2
    server, tmp = running
    status, png0 = request(server, "GET", "/api/render/mouth_0.png")
    assert status == 200
    status, body = request(server, "PUT", "/api/poses/mouth_0", {"pose": {"jawOpen": 0.0, "mouthSmile_L": 0.9}})
    assert status == 200, body
    poses = read_poses(tmp / "poses.json", list(SHAPES))
    assert poses["regions"]["mouth"]["keys"]["mouth_0"] == {"mouthSmile_L": 0.9}      # zeros dropped
    assert poses["regions"]["eyes"]["keys"]["eyes_0"]["eyeBlink_L"] == pytest.approx(1.0, abs=0.03)  # others kept
    status, png1 = request(server, "GET", "/api/render/mouth_0.png")
    a, b = (cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_COLOR) for p in (png0, png1))
    assert a.shape == (96, 96, 3) and np.abs(a.astype(int) - b).sum() > 0       # the pose changed the render


@pytest.mark.parametrize("path, body, headers, code", [
    ("/api/poses/mouth_9", {"pose": {"jawOpen": 0.5}}, None, 404),                    # no such key
    ("/api/poses/mouth_0", {"pose": {"eyeBlink_L": 0.5}}, None, 400),                 # another region's shape
    ("/api/poses/mouth_0", {"pose": {"tongueOut": 0.5}}, None, 400),                  # not a rig shape
    ("/api/poses/mouth_0", {"pose": {"jawOpen": 1.5}}, None, 400),                    # outside the range
    ("/api/poses/mouth_0", {"pose": {"jawOpen": "x"}}, None, 400),                    # not a number
    ("/api/poses/mouth_0", b'{"pose": {"jawOpen": NaN}}', None, 400),                 # not finite
    ("/api/poses/mouth_0", {"pose": [0.5]}, None, 400),                               # not an object
    ("/api/poses/mouth_0", {"pose": {"jawOpen": 0.5}}, {"Content-Type": "text/plain"}, 415),
    ("/api/poses/mouth_0", {"pose": {"jawOpen": 0.5}}, {"Host": "evil.example:80"}, 403),
    ("/api/poses/../../etc/passwd", {"pose": {}}, None, 404),
    ("/api/render/../poses.json", None, None, 404),
])
def test_bad_requests_are_refused_and_nothing_written(running, path, body, headers, code):
    server, tmp = running
    before = {p: p.read_bytes() for p in tmp.rglob("*") if p.is_file()}
    status, _ = request(server, "PUT" if body is not None else "GET", path, body, headers)
    assert status == code
    assert {p: p.read_bytes() for p in tmp.rglob("*") if p.is_file()} == before


def test_other_methods_are_refused(running):
    server, _ = running
    assert request(server, "POST", "/api/poses/mouth_0", {"pose": {}})[0] == 405
    assert request(server, "DELETE", "/api/poses/mouth_0")[0] == 405


def test_check_pose_names_the_problem():
    lib = {"range": [0.0, 1.0], "regions": {"mouth": {"shapes": ["jawOpen"], "keys": {"mouth_0": {}}}}}
    assert check_pose(lib, "mouth_0", {"jawOpen": 0.25}) == ("mouth", {"jawOpen": 0.25})
    with pytest.raises(Exception, match="outside the rig's range"):
        check_pose(lib, "mouth_0", {"jawOpen": -0.1})
    with pytest.raises(Exception, match="no key"):
        check_pose(lib, "eyes_0", {})


def test_pose_edit_command_refuses_a_bad_library_naming_it(tmp_path, capsys):
    rig, _ = write_toy_rig(tmp_path / "rig")
    (tmp_path / "poses.json").write_text('{"format": "something-else"}')
    assert main(["pose-edit", str(tmp_path / "poses.json"), "--rig", str(rig), "--port", "0"]) == 2
    assert "poses.json" in capsys.readouterr().err


def test_a_save_that_cannot_be_written_is_an_http_error_and_changes_nothing(running, monkeypatch):
    """issue 37: a PUT whose POSES.json cannot be written answers 507 with one line naming the file;
    the server keeps serving and its library stays what the file holds."""
    import errno

    import keyshape.base.formats.poses as poses_mod
    server, tmp = running
    before = (tmp / "poses.json").read_bytes()
    lib0 = json.loads(request(server, "GET", "/api/library")[1])

    def full(path, library):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(poses_mod, "write_poses", full)
    status, body = request(server, "PUT", "/api/poses/mouth_0", {"pose": {"jawOpen": 0.0, "mouthSmile_L": 0.9}})
    err = json.loads(body)["error"]
    assert status == 507 and "poses.json" in err and "\n" not in err
    assert (tmp / "poses.json").read_bytes() == before
    status, body = request(server, "GET", "/api/library")
    assert status == 200 and json.loads(body) == lib0                # not the unsaved value
