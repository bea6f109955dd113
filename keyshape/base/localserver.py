"""The safety rules and plumbing shared by keyshape's small local web pages.

Design notes and figures: docs/reliability.md, "Notes on the code", ``keyshape/base/localserver.py``.
"""
from __future__ import annotations

import errno
import ipaddress
import json
import signal
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote

from keyshape.base.errors import InputError, KeyshapeError

#: largest JSON body accepted (bytes)
MAX_BODY = 1 << 20
#: ``Host`` header names served
LOCAL_HOSTS = {"127.0.0.1", "localhost", "[::1]", "::1"}
#: returned by :meth:`LocalHandler.read_json_body` when it has already answered with an error
NO_BODY = object()


def is_loopback(address: str) -> bool:
    """Whether ``address`` (an IP string) is a loopback address (127.0.0.0/8, ::1, ::ffff:127.x)."""
    try:
        ip = ipaddress.ip_address(address.split("%")[0])
    except ValueError:
        return False
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback


def page_files(folder: Path, html: str = "index.html", js: str = "app.js") -> dict[str, tuple[Path, str]]:
    """URL path -> (file, content type) for a page folder holding the page ``html``, ``js`` and style.css
    (served as ``/``, ``/index.html``, ``/app.js`` and ``/style.css``)."""
    page = (folder / html, "text/html; charset=utf-8")
    return {"/": page, "/index.html": page,
            "/app.js": (folder / js, "text/javascript; charset=utf-8"),
            "/style.css": (folder / "style.css", "text/css; charset=utf-8")}


class LocalHandler(BaseHTTPRequestHandler):
    """Request handler with the local-only checks and JSON helpers (subclass and add the verbs)."""

    protocol_version = "HTTP/1.1"
    #: seconds a connection may stay silent (a body shorter than its Content-Length must not hold a thread)
    timeout = 10.0

    def log_message(self, fmt, *args):  # quiet unless asked
        if getattr(self.server, "verbose", False):
            super().log_message(fmt, *args)

    def send_body(self, status: int, body: bytes, ctype: str = "application/json") -> None:
        """Answer with ``body`` (never cached, never sniffed)."""
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        self.wfile.write(body)

    def send_json(self, status: int, obj) -> None:
        self.send_body(status, json.dumps(obj).encode())

    def send_error_json(self, status: int, message: str) -> None:
        self.send_json(status, {"error": message})

    def is_local(self) -> bool:
        """Whether the peer and the ``Host`` header are local; answers 403 when not."""
        if not is_loopback(self.client_address[0]):
            self.send_error_json(HTTPStatus.FORBIDDEN, "only local connections are served")
            return False
        host = (self.headers.get("Host") or "").strip().lower()
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        if name not in LOCAL_HOSTS:
            self.send_error_json(HTTPStatus.FORBIDDEN, f"Host {host!r} is not local")
            return False
        return True

    def send_page_file(self, path: str, files: dict[str, tuple[Path, str]]) -> bool:
        """Serve ``path`` if it is one of the page's ``files``; whether it was."""
        if path not in files:
            return False
        file, ctype = files[path]
        self.send_body(HTTPStatus.OK, file.read_bytes(), ctype)
        return True

    def read_json_body(self, what: str, expected: str):
        """The request's JSON body, or :data:`NO_BODY` after answering with the error.

        ``what`` names the content in the 415 message ("the points"); ``expected`` is the
        400 message for a body that is not JSON.
        """
        if (self.headers.get("Content-Type") or "").split(";")[0].strip() != "application/json":
            self.send_error_json(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, f"send {what} as application/json")
            return NO_BODY
        try:
            length = int(self.headers.get("Content-Length") or -1)
        except ValueError:
            length = -1
        if not 0 < length <= MAX_BODY:
            self.send_error_json(HTTPStatus.REQUEST_ENTITY_TOO_LARGE if length > MAX_BODY
                                 else HTTPStatus.LENGTH_REQUIRED, "body must be JSON under 1 MB with a Content-Length")
            return NO_BODY
        try:
            raw = self.rfile.read(length)
        except OSError:                           # timed out: the client sent less than it announced
            self.close_connection = True
            return NO_BODY
        if len(raw) < length:
            self.close_connection = True
            self.send_error_json(HTTPStatus.BAD_REQUEST, f"body shorter than its Content-Length ({len(raw)} < {length})")
            return NO_BODY
        try:
            return json.loads(raw)
        except (ValueError, RecursionError):      # bad JSON, not UTF-8, an integer of > 4300 digits
            self.send_error_json(HTTPStatus.BAD_REQUEST, expected)
            return NO_BODY

    #: GET routing of a page with rendered panels, set by a subclass: its static files, the JSON route of
    #: the server's ``page_data()``; ``/api/render/NAME.png`` goes to :meth:`get_render`
    page_files: dict[str, tuple[Path, str]] = {}
    data_path: str | None = None

    def get_render(self, name: str) -> None:
        """Answer ``/api/render/NAME.png`` (404 unless a subclass overrides)."""
        self.send_error_json(HTTPStatus.NOT_FOUND, "not found")

    def do_GET(self) -> None:  # noqa: N802
        """Local only: the page's files, its JSON data (under the server's lock), its rendered panels."""
        if not self.is_local():
            return
        path = self.path.split("?", 1)[0]
        if self.send_page_file(path, self.page_files):
            return
        if self.data_path is not None and path == self.data_path:
            with self.server.lock:
                self.send_json(HTTPStatus.OK, self.server.page_data())
        elif path.startswith("/api/render/") and path.endswith(".png"):
            self.get_render(unquote(path[len("/api/render/"):-len(".png")]))
        else:
            self.send_error_json(HTTPStatus.NOT_FOUND, "not found")

    #: PUT routing, set by a subclass: the URL prefix of the one kind of write, what it is, the 400
    #: message for a body of the wrong form, and the 405 message for any other URL
    put_prefix: str | None = None
    put_what = "the data"
    put_expected = "expected a JSON object"
    put_refused = "this page writes nothing"

    def put_target(self, name: str):
        """The item ``name`` (the URL after :attr:`put_prefix`) names, or :data:`NO_BODY` after
        answering (404). Subclasses override."""
        self.send_error_json(HTTPStatus.NOT_FOUND, f"no {name!r} here")
        return NO_BODY

    def put(self, target, body) -> dict:
        """Check and save ``body`` for ``target``; the JSON answer. A :class:`KeyshapeError` is a
        400 with its message, an ``OSError`` (the file cannot be written) a 507 or 500 with one line
        naming the file; either way the server's state stays what the file holds."""
        raise NotImplementedError

    def do_PUT(self) -> None:  # noqa: N802
        """The one write of a page: local only, routed by :attr:`put_prefix`, checked by :meth:`put`;
        every failure is an HTTP error with a one-line ``{"error": ...}`` the page shows."""
        if not self.is_local():
            return
        path = self.path.split("?", 1)[0]
        if self.put_prefix is None or not path.startswith(self.put_prefix):
            self.send_error_json(HTTPStatus.METHOD_NOT_ALLOWED, self.put_refused)
            return
        target = self.put_target(unquote(path[len(self.put_prefix):]))
        if target is NO_BODY:
            return
        body = self.read_json_body(self.put_what, self.put_expected)
        if body is NO_BODY:
            return
        try:
            reply = self.put(target, body)
        except KeyshapeError as exc:
            self.send_error_json(HTTPStatus.BAD_REQUEST, str(exc))
            return
        except OSError as exc:
            from keyshape.base.files import describe_os_error
            status = HTTPStatus.INSUFFICIENT_STORAGE if exc.errno in (errno.ENOSPC, errno.EDQUOT) \
                else HTTPStatus.INTERNAL_SERVER_ERROR
            self.send_error_json(status, f"not saved: {describe_os_error(exc)}")
            return
        self.send_json(HTTPStatus.OK, reply)

    def _refuse(self) -> None:
        if self.is_local():
            self.send_error_json(HTTPStatus.METHOD_NOT_ALLOWED, "method not allowed")

    do_POST = do_DELETE = do_PATCH = _refuse  # noqa: N815


class LocalServer(ThreadingHTTPServer):
    """A threading HTTP server on ``127.0.0.1:port`` (0: any free port) with :class:`LocalHandler`-style handlers."""

    daemon_threads = True

    def __init__(self, port: int, handler: type[LocalHandler]):
        super().__init__(("127.0.0.1", int(port)), handler)

    @property
    def port(self) -> int:
        return self.server_address[1]

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"


def listen(make, port: int):
    """``make()`` (a :class:`LocalServer` constructor call); a port in use is a one-line error."""
    try:
        return make()
    except OSError as exc:
        if exc.filename is not None or exc.errno not in (errno.EADDRINUSE, errno.EACCES, errno.EADDRNOTAVAIL):
            raise                                  # a file the server reads, not the socket
        raise InputError(f"cannot listen on 127.0.0.1:{port} ({exc.strerror}): try --port 0") from None


def serve_until_stopped(server: LocalServer) -> None:
    """Serve until Ctrl-C or SIGTERM (a plain ``kill`` stops it cleanly too), then close the server."""

    def _stop(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, _stop)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old)
        server.server_close()
