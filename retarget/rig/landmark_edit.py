"""A tiny local web page for correcting a rig's landmarks (a keyshape-rig-landmarks file) by hand.

``keyshape rig-check``'s page (docs/formats.md, "Correcting a point"): a click puts a point on the rig vertex under it
(:meth:`LandmarkServer.pick`) and rewrites LANDMARKS.json atomically; nothing else is written. The safety rules are
:mod:`keyshape.base.localserver`'s.
"""
from __future__ import annotations

import threading
from http import HTTPStatus
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.localserver import NO_BODY, LocalHandler, LocalServer, listen, page_files, serve_until_stopped

PAGE_FILES = page_files(Path(__file__).parent / "pose_page", "landmarks.html", "landmarks.js")
#: the port the page is served on when free (else any free one)
PORT = 8767
#: a click picks among the visible vertices within this many pixels of it
PICK_RADIUS = 8
#: the contours whose two sides a click must not confuse: contour -> (shape name keys telling the sides
#: apart, the points of the side that those shapes move down the more); each side's points are the
#: contour's points between its corners (the scheme's first point and the one midway)
SIDES = {"lip_outer": (("jawopen",), "lower"), "lip_inner": (("jawopen",), "lower"),
         "eye_left": (("eyeblinkleft", "eyeblinkright"), "upper"),
         "eye_right": (("eyeblinkleft", "eyeblinkright"), "upper")}
#: vertices near a click are on both sides when the telling shapes move them down by amounts this far
#: apart (a fraction of the shapes' largest motion)
SIDE_GAP = 0.25


def point_sides(scheme) -> dict[int, tuple[str, str]]:
    """{point: (contour, "upper" or "lower")} for the points of :data:`SIDES`' contours between their corners
    (a closed contour starts at one corner, runs along the upper side to the other corner, midway, and back)."""
    out = {}
    for name in SIDES:
        pts = scheme.contours.get(name)
        if not pts:
            continue
        half = len(pts) // 2
        for k, p in enumerate(pts):
            if k not in (0, half):
                out[int(p)] = (name, "upper" if k < half else "lower")
    return out


def check_move(body, n_points: int, point: int, n_panels: int, n_vertices: int):
    """Validate a point move: returns ``("vertex", v)`` or ``("at", panel, x, y)``.

    Raises :class:`InputError` for a body that is not ``{"vertex": int}`` or ``{"panel": int, "at": [x, y]}``
    with a panel, a vertex and pixel coordinates in range.
    """
    def integer(v, what, hi):
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < hi:
            raise InputError(f"point {point}: {what} must be an integer from 0 to {hi - 1}, not {str(v)[:40]!r}")
        return v

    if not 0 <= point < n_points:
        raise InputError(f"no point {point}: the scheme has {n_points}")
    if not isinstance(body, dict):
        raise InputError('expected {"panel": k, "at": [x, y]} or {"vertex": v}')
    if "vertex" in body:
        return "vertex", integer(body["vertex"], "vertex", n_vertices)
    if "panel" not in body or "at" not in body:
        raise InputError('expected {"panel": k, "at": [x, y]} or {"vertex": v}')
    panel = integer(body["panel"], "panel", n_panels)
    at = body["at"]
    ok = isinstance(at, list) and len(at) == 2 and all(
        not isinstance(x, bool) and isinstance(x, (int, float)) for x in at)
    try:
        ok = ok and bool(np.isfinite(np.asarray(at, np.float64)).all())
    except OverflowError:                   # an integer beyond the float range
        ok = False
    if not ok:
        raise InputError(f"point {point}: \"at\" must be two finite pixel coordinates [x, y]")
    return "at", panel, float(at[0]), float(at[1])


class LandmarkHandler(LocalHandler):
    """Request handler; the server object carries the rig, the landmarks and the panels."""

    server_version = "keyshape-rig-landmarks"

    page_files = PAGE_FILES
    data_path = "/api/landmarks"

    def get_render(self, k: str) -> None:
        if not (k.isascii() and k.isdigit() and len(k) < 6 and int(k) < len(self.server.captions)):
            self.send_error_json(HTTPStatus.NOT_FOUND, f"no panel {k!r}")
        else:
            self.send_body(HTTPStatus.OK, self.server.render_png(int(k)), "image/png")

    put_prefix = "/api/points/"
    put_what = "the point"
    put_expected = 'expected {"panel": k, "at": [x, y]} or {"vertex": v}'
    put_refused = "only landmark points can be written"

    def put_target(self, name: str):
        if not (name.isascii() and name.isdigit() and len(name) < 6 and int(name) < self.server.W.shape[0]):
            self.send_error_json(HTTPStatus.NOT_FOUND, f"no point {name[:40]!r} in the scheme")
            return NO_BODY
        return int(name)

    def put(self, point: int, body) -> dict:
        return self.server.move(point, body)


class LandmarkServer(LocalServer):
    """The landmark-correction server for one rig (docs/formats.md, "Correcting a point").

    Parameters
    ----------
    path : the landmarks file (keyshape-rig-landmarks) each move rewrites
    rig : :class:`~keyshape.retarget.rig.model.Rig` with its mesh
    W : (n_points, n_vertices) the landmarks to start from (rows summing to 1)
    scheme : :class:`keyshape.base.schemes.Scheme`
    port : TCP port on 127.0.0.1 (0: any free port)
    size : side of each panel's image in pixels
    """

    def __init__(self, path: str | Path, rig, W: np.ndarray, scheme, port: int = 0, size: int = 420,
                 verbose: bool = False):
        from keyshape.base.raster import rasterize
        from keyshape.retarget.rig.landmarks import landmark_entries, panel_curves
        from keyshape.retarget.output.preview import RigRenderer
        from keyshape.retarget.targets.target_set import name_key

        self.path = Path(path)
        self.rig, self.scheme, self.verbose = rig, scheme, verbose
        self.W = np.asarray(W, np.float64).copy()
        self.lock = threading.Lock()
        self.captions, self.curves = panel_curves(rig)
        # framed on the landmarks' vertices in every panel; the points are drawn by the page, not in the image
        self.renderer = RigRenderer(rig, (size, size), vertices=np.flatnonzero(self.W.any(axis=0))).fit(self.curves)
        self.posed = rig.evaluate(self.curves)                            # (n_panels, n_vertices, 3)
        projected = [self.renderer.camera_.project(v) for v in self.posed]
        self.xy = np.stack([p[:, :2] for p in projected])                # (n_panels, n_vertices, 2) pixels
        # each panel's visible vertices per pixel: the nearest triangle's (z-buffer)
        tri = self.renderer.tri_fit_
        self.cover = []
        for p in projected:                                               # 4 panels
            f = rasterize(p[:, :2], -p[:, 2], tri, size, size)
            self.cover.append((f.pixel, tri[f.triangle]))
        self.size = size
        keys = [name_key(n) for n in rig.names]
        self.sides = point_sides(scheme)
        # each side contour's telling motion: how far down its shapes move each vertex, relative to their largest
        self.down = {}
        for name, (shapes, _) in SIDES.items():
            idx = [j for j, k in enumerate(keys) if k in shapes]
            if idx:
                d = -rig.deltas[idx, :, 1].sum(axis=0)
                self.down[name] = d / max(float(np.abs(d).max()), 1e-300)
        self._pngs: dict[int, bytes] = {}
        self._entries = landmark_entries
        super().__init__(port, LandmarkHandler)

    def places(self, W: np.ndarray) -> list:
        """Every point's place (pixels, two decimals) in each panel for landmark rows ``W``."""
        return np.round(np.einsum("pv,kvc->kpc", W, self.xy), 2).tolist()

    def page_data(self) -> dict:
        """What the page needs: the file, the panels, each point's place in each panel, the contours."""
        return {"file": self.path.name, "scheme": self.scheme.name, "size": self.size, "panels": self.captions,
                "points": self.places(self.W),
                "contours": {k: list(map(int, v)) for k, v in self.scheme.contours.items()},
                "closed": {k: bool(self.scheme.closed.get(k, False)) for k in self.scheme.contours},
                "sides": {str(p): s for p, s in self.sides.items()}}

    def pick(self, point: int, panel: int, x: float, y: float) -> int:
        """The rig vertex a click at pixel (x, y) of ``panel`` puts ``point`` on: of the vertices of the triangles
        seen within :data:`PICK_RADIUS` pixels of the click, the nearest to it in that panel; for a point on
        one side of a lip or lid (:func:`point_sides`), where the vertices there are on both sides (the
        telling shapes move them down by amounts more than :data:`SIDE_GAP` apart: the lips of a
        closed-mouth neutral), only those on the point's side.

        Raises :class:`InputError` when no surface of the rig is seen near the click.
        """
        pixel, corners = self.cover[panel]
        px, py = pixel % self.size, pixel // self.size
        seen = (px - x) ** 2 + (py - y) ** 2 <= PICK_RADIUS ** 2
        cand = np.unique(corners[seen])
        if not len(cand):
            raise InputError(f"point {point}: no surface of the rig within {PICK_RADIUS} pixels of ({x:.0f}, {y:.0f}) "
                             f"in panel {self.captions[panel]!r}")
        if point in self.sides and self.sides[point][0] in self.down:
            contour, side = self.sides[point]
            d = self.down[contour][cand]
            if d.max() - d.min() > SIDE_GAP:
                mid = 0.5 * (d.max() + d.min())
                more = SIDES[contour][1]                                  # the side moved down the more
                cand = cand[(d > mid) if side == more else (d <= mid)]
        dist = np.linalg.norm(self.xy[panel, cand] - [x, y], axis=1)
        return int(cand[np.argmin(dist)])

    def move(self, point: int, body) -> dict:
        """Check a move (:func:`check_move`), put the point on its vertex and rewrite the file atomically;
        the answer: the point, its vertex, every point's place in each panel, and what the landmarks'
        geometry says is wrong now, if anything (the file is saved either way: a correction may take
        several moves)."""
        from keyshape.base.files import user_save
        from keyshape.base.formats.poses import write_rig_landmarks
        from keyshape.retarget.rig.landmarks import landmark_problem
        how = check_move(body, self.W.shape[0], point, len(self.captions), self.rig.n_vertices)
        v = how[1] if how[0] == "vertex" else self.pick(point, *how[1:])
        with self.lock:
            W = self.W.copy()
            W[point] = 0.0
            W[point, v] = 1.0
            with user_save():
                write_rig_landmarks(self.path, self.scheme.name, self.rig.n_vertices, self._entries(W))
            self.W = W                              # an OSError above leaves the points what the file holds
            problem = landmark_problem(W @ self.rig.neutral, self.scheme, self.rig.neutral.mean(axis=0))
            return {"saved": point, "vertex": v, "problem": problem,
                    "points": self.places(W)}

    def render_png(self, panel: int) -> bytes:
        """The rig in ``panel``'s shape, as PNG bytes (rendered once)."""
        import cv2
        with self.lock:
            if panel not in self._pngs:
                ok, buf = cv2.imencode(".png", self.renderer.render_curves(self.curves[panel]))
                self._pngs[panel] = buf.tobytes()
            return self._pngs[panel]


def serve(path: str | Path, rig, W: np.ndarray, scheme) -> None:
    """Serve the page until Ctrl-C (or SIGTERM) on :data:`PORT`, or any free port when that one is taken;
    prints the address."""
    try:
        server = listen(lambda: LandmarkServer(path, rig, W, scheme, PORT), PORT)
    except InputError:
        server = LandmarkServer(path, rig, W, scheme, 0)
    print(f"correct the landmarks at {server.url} (Ctrl-C to stop); every change is saved to {server.path}",
          flush=True)
    serve_until_stopped(server)
