"""Label-correction server: serves the page and points, writes only NNNNNN.pts in the label folder."""
from __future__ import annotations

import json
import socket

import numpy as np
import pytest

from keyshape.base.formats.labels import read_pts
from keyshape.tracker.labelling import server as srv_mod
from label_helpers import make_folder
from server_helpers import request, serving


def snapshot(root):
    return {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def running(tmp_path):
    folder = make_folder(tmp_path)
    with serving(srv_mod.LabelServer(folder, 0)) as server:
        yield server, tmp_path


def test_serves_page_session_points_and_frames(running):
    server, _ = running
    st, body = request(server, "GET", "/")
    assert st == 200 and b"app.js" in body
    st, body = request(server, "GET", "/api/session")
    sess = json.loads(body)
    assert sess["frames"] == ["000005", "000040"] and sess["scheme"]["n_points"] == 48
    st, body = request(server, "GET", "/api/points/000040.pts")
    np.testing.assert_allclose(json.loads(body)["points"], read_pts(server.folder / "000040.pts"))
    st, body = request(server, "GET", "/frames/000005.png")
    assert st == 200 and body[:4] == b"\x89PNG"


def test_put_writes_that_pts_file_only(running):
    server, root = running
    before = snapshot(root)
    pts = read_pts(server.folder / "000005.pts")
    pts[12] += [3.25, -1.5]
    st, body = request(server, "PUT", "/api/points/000005.pts", {"points": pts.tolist()})
    assert st == 200, body
    after = snapshot(root)
    changed = [p for p in after if before.get(p) != after[p]]
    assert changed == [server.folder / "000005.pts"] and set(after) == set(before)
    np.testing.assert_allclose(read_pts(server.folder / "000005.pts"), pts, atol=1e-3)


@pytest.mark.parametrize("path", [
    "/api/points/../evil.pts", "/api/points/..%2F..%2F000005.pts", "/api/points/%2e%2e/000005.pts",
    "/api/points//tmp/000005.pts", "/api/points/000006.pts", "/api/points/5.pts",
    "/api/points/000005.pts.bak", "/api/points/000005.txt", "/frames/000005.pts", "/session.json",
    "/api/points/0000005.pts",
])
def test_path_traversal_and_other_names_refused(running, path):
    server, root = running
    before = snapshot(root)
    pts = read_pts(server.folder / "000005.pts").tolist()
    st, _ = request(server, "PUT", path, {"points": pts})
    assert st in (404, 405)
    assert snapshot(root) == before
    st, _ = request(server, "GET", path.replace("000005.pts", "../session.json"))
    assert st == 404


def test_bad_bodies_refused(running):
    server, root = running
    before = snapshot(root)
    good = read_pts(server.folder / "000005.pts").tolist()
    assert request(server, "PUT", "/api/points/000005.pts", {"points": good[:10]})[0] == 400
    bad = [list(p) for p in good]
    bad[0][0] = float("nan")
    assert request(server, "PUT", "/api/points/000005.pts", json.dumps({"points": bad}).encode())[0] == 400
    assert request(server, "PUT", "/api/points/000005.pts", b"not json")[0] == 400
    assert request(server, "PUT", "/api/points/000005.pts", json.dumps({"points": good}).encode(),
                   {"Content-Type": "text/plain"})[0] == 415  # what a cross-site form could send
    assert request(server, "POST", "/api/points/000005.pts", {"points": good})[0] == 405
    assert request(server, "DELETE", "/api/points/000005.pts")[0] == 405
    assert snapshot(root) == before


def test_non_local_host_header_refused(running):
    server, root = running
    before = snapshot(root)
    good = read_pts(server.folder / "000005.pts").tolist()
    st, body = request(server, "GET", "/api/session", headers={"Host": "evil.example:80"})
    assert st == 403 and b"not local" in body
    assert request(server, "PUT", "/api/points/000005.pts", {"points": good},
                   {"Host": "evil.example"})[0] == 403
    assert snapshot(root) == before


def test_non_local_peer_refused(running, monkeypatch):
    server, root = running
    before = snapshot(root)
    good = read_pts(server.folder / "000005.pts").tolist()
    import keyshape.base.localserver as local_mod
    monkeypatch.setattr(local_mod, "is_loopback", lambda addr: False)  # as if the peer were remote
    st, body = request(server, "GET", "/")
    assert st == 403 and b"only local" in body
    assert request(server, "PUT", "/api/points/000005.pts", {"points": good})[0] == 403
    assert snapshot(root) == before


def test_bound_to_loopback_only(running):
    server, _ = running
    assert server.server_address[0] == "127.0.0.1"
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.connect(("10.255.255.255", 1))  # no packet sent: just picks the outward interface
        ip = s.getsockname()[0]
    except OSError:
        ip = None
    finally:
        s.close()
    if ip is None or srv_mod.is_loopback(ip):
        pytest.skip("no non-loopback interface to try")
    with pytest.raises(OSError):
        socket.create_connection((ip, server.port), timeout=2).close()


def test_is_loopback():
    assert srv_mod.is_loopback("127.0.0.1") and srv_mod.is_loopback("::1")
    assert srv_mod.is_loopback("::ffff:127.0.0.1") and srv_mod.is_loopback("127.3.2.1")
    assert not srv_mod.is_loopback("192.168.1.4") and not srv_mod.is_loopback("::ffff:10.0.0.1")
    assert not srv_mod.is_loopback("localhost.evil") and not srv_mod.is_loopback("")


def test_missing_session_named(tmp_path):
    from keyshape.base.errors import MissingFileError
    with pytest.raises(MissingFileError, match="session.json"):
        srv_mod.LabelServer(tmp_path, 0)


def test_implausible_coordinates_refused(running):
    server, root = running
    before = snapshot(root)
    pts = read_pts(server.folder / "000005.pts")
    pts[3] = [1e300, 5.0]
    st, body = request(server, "PUT", "/api/points/000005.pts", {"points": pts.tolist()})
    assert st == 400 and b"beyond" in body and snapshot(root) == before


def test_short_body_does_not_hold_a_thread(running, monkeypatch):
    server, root = running
    monkeypatch.setattr(srv_mod.LabelHandler, "timeout", 0.5)
    before = snapshot(root)
    s = socket.create_connection(("127.0.0.1", server.port), timeout=5)
    s.sendall(b"PUT /api/points/000005.pts HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
              b"Content-Length: 500\r\n\r\n{\"points\": [")
    s.settimeout(5)
    assert s.recv(100) == b""          # the server gave up on the connection after its timeout
    s.close()
    st, _ = request(server, "GET", "/api/session")        # and still serves
    assert st == 200 and snapshot(root) == before


def test_corrupt_pts_gives_an_error_response(running):
    server, _ = running
    (server.folder / "000040.pts").write_text("version: 1\nn_points: 48\n{\n1 2\n")
    st, body = request(server, "GET", "/api/points/000040.pts")
    assert st == 422 and b"000040.pts" in body and b"closing brace" in body
    st, _ = request(server, "GET", "/api/session")
    assert st == 200


def test_degenerate_points_and_unwritable_saves_are_http_errors(running, monkeypatch):
    """issue 37: 53 identical points are refused (400); a .pts that cannot be written is a 507 with one
    line naming it, and the server keeps serving what the file holds."""
    import errno

    import keyshape.base.formats.labels as labels_mod
    server, root = running
    before = snapshot(root)
    n = server.scheme.n_points
    st, body = request(server, "PUT", "/api/points/000005.pts", {"points": [[100.0, 100.0]] * n})
    assert st == 400 and "collapsed" in json.loads(body)["error"]

    def full(path, points):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(labels_mod, "write_pts", full)
    pts = read_pts(server.folder / "000005.pts")
    st, body = request(server, "PUT", "/api/points/000005.pts", {"points": (pts + 1).tolist()})
    err = json.loads(body)["error"]
    assert st == 507 and "000005.pts" in err and "\n" not in err
    assert snapshot(root) == before
    st, body = request(server, "GET", "/api/points/000005.pts")
    assert st == 200 and np.allclose(json.loads(body)["points"], pts)


def test_the_contact_sheet_survives_a_collapsed_label_file(tmp_path):
    """issue 37: a hand-edited .pts with every point on one spot no longer crashes the redraw at Ctrl-C."""
    from keyshape.base.formats.labels import write_pts
    from keyshape.base.schemes import load_scheme
    from keyshape.tracker.labelling.prepare import write_contact_sheet
    folder = make_folder(tmp_path)
    write_pts(folder / "000005.pts", np.full((48, 2), 50.0))
    assert write_contact_sheet(folder, [5, 40], load_scheme("contours48")).is_file()
