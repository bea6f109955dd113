"""A tiny local web server for correcting landmark labels in a browser.

Standard library only (``http.server``). It serves the static page in
``page/``, the label folder's frame images and points, and accepts one kind of
write: ``PUT /api/points/NNNNNN.pts`` with a JSON body ``{"points": [[x, y],
...]}``, which replaces that frame's ``.pts`` file atomically. Nothing else is
ever written.

Safety:

* it binds to ``127.0.0.1`` only, and also refuses (403) any connection whose
  peer address is not a loopback address, or whose ``Host`` header is not a
  loopback name (blocks DNS-rebinding pages from reaching it);
* a ``.pts`` name must match ``^\\d{6}\\.pts$`` and be one of the session's frames
  (so no ``../`` or absolute path can get through); frame images likewise;
* writes need ``Content-Type: application/json`` (a cross-site form cannot send
  it without a CORS preflight, which this server never grants), a body under
  1 MB, and exactly the scheme's number of finite points.

Label folder layout (made by ``keyshape label``)::

    DIR/session.json        scheme name, video, chosen frames
    DIR/frames/000123.png   the chosen frames
    DIR/000123.pts          their points (what the page edits)
    DIR/contact_sheet.png   the frames with their points, to check by eye
"""
from __future__ import annotations

import ipaddress
import json
import re
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, KeyshapeError, require_dir, require_file

PAGE_DIR = Path(__file__).parent / "page"
PAGE_FILES = {"/": ("index.html", "text/html; charset=utf-8"),
              "/index.html": ("index.html", "text/html; charset=utf-8"),
              "/app.js": ("app.js", "text/javascript; charset=utf-8"),
              "/style.css": ("style.css", "text/css; charset=utf-8")}
PTS_RE = re.compile(r"^(\d{6})\.pts$")
PNG_RE = re.compile(r"^(\d{6})\.png$")
MAX_BODY = 1 << 20
LOCAL_HOSTS = {"127.0.0.1", "localhost", "[::1]", "::1"}
SESSION_FILE = "session.json"


def read_session(folder: str | Path) -> dict:
    """The ``session.json`` of a label folder: ``scheme``, ``video``, ``frames``."""
    folder = require_dir(folder, "label folder")
    path = require_file(folder / SESSION_FILE, "label session (made by 'keyshape label')")
    try:
        data = json.loads(path.read_text())
        frames = [int(f) for f in data["frames"]]
        scheme = str(data["scheme"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"not a label session ({exc})", path) from None
    return {**data, "frames": frames, "scheme": scheme}


def is_loopback(address: str) -> bool:
    """Whether ``address`` (an IP string) is a loopback address (127.0.0.0/8, ::1, ::ffff:127.x)."""
    try:
        ip = ipaddress.ip_address(address.split("%")[0])
    except ValueError:
        return False
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback


#: largest coordinate saved (pixels): far beyond any frame, still refusing 1e300
MAX_COORDINATE = 1e5


class LabelHandler(BaseHTTPRequestHandler):
    """Request handler; the server object carries ``folder``, ``scheme``, ``frames``."""

    server_version = "keyshape-label"
    protocol_version = "HTTP/1.1"
    #: seconds a connection may stay silent (a body shorter than its Content-Length must not hold a thread)
    timeout = 10.0

    def log_message(self, fmt, *args):  # quiet unless asked
        if getattr(self.server, "verbose", False):
            super().log_message(fmt, *args)

    # ------------------------------------------------------------------ helpers
    def _send(self, status: int, body: bytes, ctype: str = "application/json") -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, obj) -> None:
        self._send(status, json.dumps(obj).encode())

    def _error(self, status: int, message: str) -> None:
        self._json(status, {"error": message})

    def _local(self) -> bool:
        if not is_loopback(self.client_address[0]):
            self._error(HTTPStatus.FORBIDDEN, "only local connections are served")
            return False
        host = (self.headers.get("Host") or "").strip().lower()
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        if name not in LOCAL_HOSTS:
            self._error(HTTPStatus.FORBIDDEN, f"Host {host!r} is not local")
            return False
        return True

    def _frame_of(self, name: str, pattern: re.Pattern) -> int | None:
        m = pattern.match(name)
        if not m or int(m.group(1)) not in self.server.frames:
            self._error(HTTPStatus.NOT_FOUND, f"no frame file {name!r} in this session")
            return None
        return int(m.group(1))

    # ------------------------------------------------------------------ verbs
    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        if not self._local():
            return
        path = self.path.split("?", 1)[0]
        srv = self.server
        if path in PAGE_FILES:
            name, ctype = PAGE_FILES[path]
            self._send(HTTPStatus.OK, (PAGE_DIR / name).read_bytes(), ctype)
        elif path == "/api/session":
            sch = srv.scheme
            self._json(HTTPStatus.OK, {
                "scheme": {"name": sch.name, "n_points": sch.n_points,
                           "contours": {k: list(v) for k, v in sch.contours.items()},
                           "closed": sch.closed},
                "frames": [f"{f:06d}" for f in sorted(srv.frames)],
                "video": str(srv.session.get("video", "")),
            })
        elif path.startswith("/frames/"):
            f = self._frame_of(path[len("/frames/"):], PNG_RE)
            if f is not None:
                img = srv.folder / "frames" / f"{f:06d}.png"
                if img.is_file():
                    self._send(HTTPStatus.OK, img.read_bytes(), "image/png")
                else:
                    self._error(HTTPStatus.NOT_FOUND, "frame image missing")
        elif path.startswith("/api/points/"):
            f = self._frame_of(path[len("/api/points/"):], PTS_RE)
            if f is not None:
                try:
                    pts = srv.read_points(f)
                except (KeyshapeError, OSError) as exc:   # a damaged .pts in the folder: say so, keep serving
                    self._error(HTTPStatus.UNPROCESSABLE_ENTITY, str(exc))
                    return
                self._json(HTTPStatus.OK, {"points": [[float(x), float(y)] if np.isfinite(x + y) else [None, None]
                                                      for x, y in pts]})
        else:
            self._error(HTTPStatus.NOT_FOUND, "not found")

    def do_PUT(self) -> None:  # noqa: N802
        if not self._local():
            return
        path = self.path.split("?", 1)[0]
        if not path.startswith("/api/points/"):
            self._error(HTTPStatus.METHOD_NOT_ALLOWED, "only .pts files can be written")
            return
        f = self._frame_of(path[len("/api/points/"):], PTS_RE)
        if f is None:
            return
        if (self.headers.get("Content-Type") or "").split(";")[0].strip() != "application/json":
            self._error(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "send the points as application/json")
            return
        try:
            length = int(self.headers.get("Content-Length") or -1)
        except ValueError:
            length = -1
        if not 0 < length <= MAX_BODY:
            self._error(HTTPStatus.REQUEST_ENTITY_TOO_LARGE if length > MAX_BODY else HTTPStatus.LENGTH_REQUIRED,
                        "body must be JSON under 1 MB with a Content-Length")
            return
        try:
            raw = self.rfile.read(length)
        except OSError:                           # timed out: the client sent less than it announced
            self.close_connection = True
            return
        if len(raw) < length:
            self.close_connection = True
            self._error(HTTPStatus.BAD_REQUEST, f"body shorter than its Content-Length ({len(raw)} < {length})")
            return
        try:
            body = json.loads(raw)
            pts = np.asarray(body["points"], dtype=np.float64)
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError, RecursionError):
            self._error(HTTPStatus.BAD_REQUEST, 'expected {"points": [[x, y], ...]}')
            return
        n = self.server.scheme.n_points
        if pts.shape != (n, 2) or not np.all(np.isfinite(pts)):
            self._error(HTTPStatus.BAD_REQUEST, f"expected {n} finite (x, y) points, got shape {pts.shape}")
            return
        if np.abs(pts).max() > MAX_COORDINATE:
            self._error(HTTPStatus.BAD_REQUEST, f"coordinates beyond {MAX_COORDINATE:g} pixels are not image points")
            return
        self.server.write_points(f, pts)
        self._json(HTTPStatus.OK, {"saved": f"{f:06d}.pts"})

    def _refuse(self) -> None:
        if self._local():
            self._error(HTTPStatus.METHOD_NOT_ALLOWED, "method not allowed")

    do_POST = do_DELETE = do_PATCH = _refuse  # noqa: N815


class LabelServer(ThreadingHTTPServer):
    """The label-correction server for one label folder (see module docstring).

    Parameters
    ----------
    folder : str or Path
        A label folder made by ``keyshape label`` (holds ``session.json``).
    port : int
        TCP port on 127.0.0.1 (0: any free port; see :attr:`port`).
    """

    daemon_threads = True

    def __init__(self, folder: str | Path, port: int = 0, verbose: bool = False):
        from keyshape.base.schemes import load_scheme  # noqa: PLC0415

        self.folder = Path(folder).resolve()
        self.session = read_session(self.folder)
        self.scheme = load_scheme(self.session["scheme"])
        self.frames = frozenset(self.session["frames"])
        self.verbose = verbose
        self._lock = threading.Lock()
        super().__init__(("127.0.0.1", int(port)), LabelHandler)

    @property
    def port(self) -> int:
        return self.server_address[1]

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def pts_path(self, frame: int) -> Path:
        from keyshape.base.formats.labels import pts_name  # noqa: PLC0415
        return self.folder / pts_name(frame)

    def read_points(self, frame: int) -> np.ndarray:
        """Points of ``frame`` from its .pts file; NaN where the file is missing."""
        from keyshape.base.formats.labels import read_pts  # noqa: PLC0415
        p = self.pts_path(frame)
        if p.is_file():
            return self.scheme.check_shapes(read_pts(p), str(p))
        return np.full((self.scheme.n_points, 2), np.nan)

    def write_points(self, frame: int, points: np.ndarray) -> None:
        """Replace ``frame``'s .pts file atomically (the only write this server does)."""
        from keyshape.base.formats.labels import write_pts  # noqa: PLC0415
        with self._lock:
            write_pts(self.pts_path(frame), points)
