"""The landmark-correction page (``keyshape rig-check RIG -o LANDMARKS.json``, issue 39): serves the rig's panels and
points, moves a point to the vertex clicked (on the point's own lip), saves only the landmarks file, refuses bad
requests."""
from __future__ import annotations

import json

import numpy as np
import pytest

from keyshape.base.formats.poses import read_rig_landmarks, write_rig_landmarks
from keyshape.base.schemes import load_scheme
from keyshape.cli import main
from remesh_rig import remeshed_ict_rig
from keyshape.retarget.rig.landmark_edit import LandmarkServer, point_sides
from keyshape.retarget.rig.model import load_rig
from server_helpers import request, serving

SCHEME = load_scheme("contours48")


@pytest.fixture(scope="module")
def remeshed(tmp_path_factory):
    d = tmp_path_factory.mktemp("rig")
    r = remeshed_ict_rig(d / "rig", seed=3)
    return r, load_rig(r["rig"], cache=False)


@pytest.fixture
def running(remeshed, tmp_path):
    r, rig = remeshed
    _, truth = read_rig_landmarks(r["landmarks"])
    with serving(LandmarkServer(tmp_path / "lm.json", rig, truth, SCHEME, port=0, size=200)) as server:
        yield server, tmp_path, truth


def _saved(path):
    return read_rig_landmarks(path)[1]


def test_page_panels_and_points_are_served(running):
    import cv2
    server, _, _ = running
    status, body = request(server, "GET", "/")
    assert status == 200 and b"app.js" in body and b"landmarks" in body
    assert request(server, "GET", "/app.js")[0] == request(server, "GET", "/style.css")[0] == 200
    data = json.loads(request(server, "GET", "/api/landmarks")[1])
    assert data["panels"] == ["neutral", "blink", "jaw open", "smile"] and data["scheme"] == "contours48"
    P = np.array(data["points"])
    assert P.shape == (4, 48, 2) and (P > 0).all() and (P < 200).all()           # every point framed in every panel
    assert P[2, 46, 1] - P[2, 42, 1] > P[0, 46, 1] - P[0, 42, 1] + 5                # the jaw opens the inner lips
    status, png = request(server, "GET", "/api/render/2.png")
    assert status == 200 and cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).shape == (200, 200, 3)
    assert request(server, "GET", "/api/render/4.png")[0] == 404


def test_a_point_moved_by_vertex_or_by_click_lands_in_the_saved_file(running):
    server, tmp, truth = running
    v_upper = int(np.argmax(truth[42]))                       # the inner upper lip's middle (a vertex of the truth)
    status, body = request(server, "PUT", "/api/points/30", {"vertex": v_upper})
    assert status == 200, body
    saved = _saved(tmp / "lm.json")
    assert saved[30, v_upper] == 1.0 and np.array_equal(np.delete(saved, 30, 0), np.delete(truth, 30, 0))
    assert json.loads(body)["problem"] is None
    # a move the geometry refutes (an eye's point on the mouth) is saved, and the answer says what is wrong
    status, body = request(server, "PUT", "/api/points/12", {"vertex": v_upper})
    assert status == 200 and "not one contour" in json.loads(body)["problem"]
    assert _saved(tmp / "lm.json")[12, v_upper] == 1.0
    # a click on the jaw-open panel, at the place of the truth's vertex of point 46 (inner lower lip): that vertex
    P = np.array(json.loads(request(server, "GET", "/api/landmarks")[1])["points"])
    v_lower = int(np.argmax(truth[46]))
    status, body = request(server, "PUT", "/api/points/46", {"panel": 2, "at": P[2, 46].tolist()})
    assert status == 200 and json.loads(body)["vertex"] == v_lower, body
    assert _saved(tmp / "lm.json")[46, v_lower] == 1.0


def test_a_click_where_the_lips_touch_picks_the_points_own_lip(running, remeshed):
    """In the closed-mouth neutral the inner lips touch: the same click puts an upper-lip point on the upper lip
    (the one jawOpen leaves) and a lower-lip point on the lower lip."""
    server, tmp, truth = running
    _, rig = remeshed
    jaw = -rig.deltas[rig.names.index("jawOpen"), :, 1]
    assert point_sides(SCHEME)[42] == ("lip_inner", "upper") and point_sides(SCHEME)[46] == ("lip_inner", "lower")
    P = np.array(json.loads(request(server, "GET", "/api/landmarks")[1])["points"])
    at = (0.5 * (P[0, 42] + P[0, 46])).tolist()                                   # between them, in the neutral
    picked = {}
    for p in (42, 46):
        status, body = request(server, "PUT", f"/api/points/{p}", {"panel": 0, "at": at})
        assert status == 200, body
        picked[p] = json.loads(body)["vertex"]
    assert jaw[picked[42]] < 0.5 * jaw[int(np.argmax(truth[46]))] < jaw[picked[46]]
    saved = _saved(tmp / "lm.json")
    assert saved[42, picked[42]] == saved[46, picked[46]] == 1.0


@pytest.mark.parametrize("path, body, headers, code", [
    ("/api/points/48", {"vertex": 1}, None, 404),                                  # no such point
    ("/api/points/abc", {"vertex": 1}, None, 404),
    ("/api/points/../lm.json", {"vertex": 1}, None, 404),
    ("/api/points/%C2%B2", {"vertex": 1}, None, 404),                             # a digit int() does not read
    ("/api/points/" + "9" * 5000, {"vertex": 1}, None, 404),
    ("/api/points/3", {"vertex": -1}, None, 400),                                  # outside the rig
    ("/api/points/3", {"vertex": 10 ** 9}, None, 400),
    ("/api/points/3", {"vertex": True}, None, 400),
    ("/api/points/3", {"vertex": 1.5}, None, 400),
    ("/api/points/3", {"panel": 4, "at": [100, 100]}, None, 400),                  # no such panel
    ("/api/points/3", {"panel": 0, "at": [100]}, None, 400),
    ("/api/points/3", {"panel": 0, "at": ["x", 1]}, None, 400),
    ("/api/points/3", b'{"panel": 0, "at": [NaN, 1]}', None, 400),
    ("/api/points/3", {"panel": 0, "at": [1e30, 1e30]}, None, 400),                # no surface there
    ("/api/points/3", [1, 2], None, 400),
    ("/api/points/3", b"not json", None, 400),
    ("/api/points/3", {"vertex": 1}, {"Content-Type": "text/plain"}, 415),
    ("/api/points/3", {"vertex": 1}, {"Host": "evil.example:80"}, 403),
    ("/api/landmarks", {"vertex": 1}, None, 405),
])
def test_bad_requests_are_refused_and_nothing_written(running, path, body, headers, code):
    server, tmp, _ = running
    request(server, "PUT", "/api/points/0", {"vertex": 5})                      # the file exists
    before = {p: p.read_bytes() for p in tmp.rglob("*") if p.is_file()}
    status, answer = request(server, "PUT", path, body, headers)
    assert status == code, answer
    if code == 400:
        assert "\n" not in json.loads(answer)["error"]
    assert {p: p.read_bytes() for p in tmp.rglob("*") if p.is_file()} == before


def test_rig_check_with_a_json_output_serves_the_page_on_the_landmarks_it_writes(remeshed, tmp_path, monkeypatch, capsys):
    """``-o LANDMARKS.json``: the landmarks (here the rig's iBUG-68 list) written to that file, then the page served
    on them; another suffix is refused in one line; the output is never an input."""
    r, _ = remeshed
    served = {}
    monkeypatch.setattr("keyshape.retarget.rig.landmark_edit.serve",
                        lambda path, rig, W, scheme: served.update(path=path, W=W))
    assert main(["rig-check", str(r["rig"]), "--landmarks", str(r["ibug68"]), "-o", str(tmp_path / "fixed.json")]) == 0
    _, truth = read_rig_landmarks(r["landmarks"])
    assert str(served["path"]) == str(tmp_path / "fixed.json") and np.abs(served["W"] - truth).max() < 1e-6
    assert np.abs(_saved(tmp_path / "fixed.json") - truth).max() < 1e-6
    # a file the rig's geometry refutes (the lips upside down) is served to be corrected, said in one line
    entries = json.loads(r["landmarks"].read_text())["points"]
    write_rig_landmarks(tmp_path / "lips.json", "contours48", len(truth[0]),
                        entries[:28] + entries[34:40] + entries[28:34] + entries[40:])
    capsys.readouterr()
    assert main(["rig-check", str(r["rig"]), "--landmarks", str(tmp_path / "lips.json"), "-o",
                 str(tmp_path / "fixed2.json")]) == 0
    assert "upper points are below its lower ones" in capsys.readouterr().out
    assert np.array_equal(served["W"], read_rig_landmarks(tmp_path / "lips.json")[1])
    assert main(["rig-check", str(r["rig"]), "-o", str(tmp_path / "fixed.txt")]) == 2
    assert "landmarks file (.json)" in capsys.readouterr().err
    assert main(["rig-check", str(r["rig"]), "--landmarks", str(r["landmarks"]), "-o", str(r["landmarks"]),
                 "--overwrite"]) == 2
