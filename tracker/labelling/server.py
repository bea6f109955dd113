"""A tiny local web server for correcting landmark labels in a browser.

Serves the static page in ``page/``, the label folder's frame images and points, and accepts one write:
``PUT /api/points/NNNNNN.pts`` with ``{"points": [[x, y], ...]}`` (one of the session's frames, the scheme's
number of finite points), which replaces that ``.pts`` file atomically. The safety rules are
:mod:`keyshape.base.localserver`'s (docs/label.md, docs/reliability.md).
"""
from __future__ import annotations

import re
import threading
from http import HTTPStatus
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, KeyshapeError
from keyshape.base.formats.labels import read_session
from keyshape.base.localserver import NO_BODY, LocalHandler, LocalServer, is_loopback, page_files  # noqa: F401

PAGE_FILES = page_files(Path(__file__).parent / "page")
PTS_RE = re.compile(r"^(\d{6})\.pts$")
PNG_RE = re.compile(r"^(\d{6})\.png$")


#: largest coordinate saved (pixels): far beyond any frame, still refusing 1e300
MAX_COORDINATE = 1e5


class LabelHandler(LocalHandler):
    """Request handler; the server object carries ``folder``, ``scheme``, ``frames``."""

    server_version = "keyshape-label"

    def _frame_of(self, name: str, pattern: re.Pattern) -> int | None:
        m = pattern.match(name)
        if not m or int(m.group(1)) not in self.server.frames:
            self.send_error_json(HTTPStatus.NOT_FOUND, f"no frame file {name!r} in this session")
            return None
        return int(m.group(1))

    # ------------------------------------------------------------------ verbs
    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        if not self.is_local():
            return
        path = self.path.split("?", 1)[0]
        srv = self.server
        if self.send_page_file(path, PAGE_FILES):
            pass
        elif path == "/api/session":
            sch = srv.scheme
            self.send_json(HTTPStatus.OK, {
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
                    self.send_body(HTTPStatus.OK, img.read_bytes(), "image/png")
                else:
                    self.send_error_json(HTTPStatus.NOT_FOUND, "frame image missing")
        elif path.startswith("/api/points/"):
            f = self._frame_of(path[len("/api/points/"):], PTS_RE)
            if f is not None:
                try:
                    pts = srv.read_points(f)
                except (KeyshapeError, OSError) as exc:   # a damaged .pts in the folder: say so, keep serving
                    self.send_error_json(HTTPStatus.UNPROCESSABLE_ENTITY, str(exc))
                    return
                self.send_json(HTTPStatus.OK, {"points": [[float(x), float(y)] if np.isfinite(x + y) else [None, None]
                                                      for x, y in pts]})
        else:
            self.send_error_json(HTTPStatus.NOT_FOUND, "not found")

    put_prefix = "/api/points/"
    put_what = "the points"
    put_expected = 'expected {"points": [[x, y], ...]}'
    put_refused = "only .pts files can be written"

    def put_target(self, name: str):
        f = self._frame_of(name, PTS_RE)
        return NO_BODY if f is None else f

    def put(self, f: int, body) -> dict:
        from keyshape.tracker.commands import check_label_geometry  # noqa: PLC0415
        try:
            pts = np.asarray(body["points"], dtype=np.float64)
        except (KeyError, TypeError, ValueError, IndexError, RecursionError):
            raise InputError(self.put_expected) from None
        n = self.server.scheme.n_points
        if pts.shape != (n, 2) or not np.all(np.isfinite(pts)):
            raise InputError(f"expected {n} finite (x, y) points, got shape {pts.shape}")
        if np.abs(pts).max() > MAX_COORDINATE:
            raise InputError(f"coordinates beyond {MAX_COORDINATE:g} pixels are not image points")
        check_label_geometry(np.array([f]), pts[None], None)
        self.server.write_points(f, pts)
        return {"saved": f"{f:06d}.pts"}


class LabelServer(LocalServer):
    """The label-correction server for one label folder (see module docstring).

    Parameters
    ----------
    folder : str or Path
        A label folder made by ``keyshape label`` (holds ``session.json``).
    port : int
        TCP port on 127.0.0.1 (0: any free port; see :attr:`port`).
    """

    def __init__(self, folder: str | Path, port: int = 0, verbose: bool = False):
        from keyshape.base.schemes import load_scheme  # noqa: PLC0415

        self.folder = Path(folder).resolve()
        self.session = read_session(self.folder)
        self.scheme = load_scheme(self.session["scheme"])
        self.frames = frozenset(self.session["frames"])
        self.verbose = verbose
        self._lock = threading.Lock()
        super().__init__(port, LabelHandler)

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
        from keyshape.base.files import user_save  # noqa: PLC0415
        from keyshape.base.formats.labels import write_pts  # noqa: PLC0415
        with self._lock, user_save():
            write_pts(self.pts_path(frame), points)
