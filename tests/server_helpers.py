"""Helpers for tests of keyshape's local web pages (label correction, pose correction)."""
from __future__ import annotations

import contextlib
import http.client
import json
import threading


@contextlib.contextmanager
def serving(server):
    """Run ``server.serve_forever`` on a daemon thread; shut it down and close it afterwards."""
    t = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
    t.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()


def request(server, method, path, body=None, headers=None):
    """(status, body bytes) of one request; ``body`` dict/list is sent as JSON."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
    h = {"Content-Type": "application/json"} if body is not None else {}
    h.update(headers or {})
    data = json.dumps(body).encode() if isinstance(body, (dict, list)) else body
    conn.request(method, path, body=data, headers=h)
    r = conn.getresponse()
    out = r.status, r.read()
    conn.close()
    return out
