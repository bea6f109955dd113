"""A tiny local web page for correcting a pose library (POSES.json) by hand.

Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/rig/pose_edit.py``.
"""
from __future__ import annotations

import threading
from http import HTTPStatus
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.localserver import NO_BODY, LocalHandler, LocalServer, listen, page_files, serve_until_stopped

PAGE_FILES = page_files(Path(__file__).parent / "pose_page")


def check_pose(library: dict, key: str, pose, source=None) -> tuple[str, dict]:
    """Validate a hand-edited pose of ``key``: returns (region, {shape: weight}) without zeros.

    Raises :class:`InputError` for an unknown key, a shape outside the key's region, or a
    weight that is not a finite number within the library's ``range``.
    """
    region = next((r for r, reg in library["regions"].items() if key in reg["keys"]), None)
    if region is None:
        raise InputError(f"no key {key!r} in the pose library", source)
    if not isinstance(pose, dict):
        raise InputError(f"{key}: expected a pose object {{shape: weight}}", source)
    lo, hi = library.get("range", (0.0, 1.0))
    allowed = set(library["regions"][region]["shapes"])
    out = {}
    for s, v in pose.items():
        if s not in allowed:
            raise InputError(f"{key}: shape {s!r} is not among region {region!r}'s shapes", source)
        try:
            finite = not isinstance(v, bool) and isinstance(v, (int, float)) and np.isfinite(float(v))
        except OverflowError:           # an integer beyond the float range
            finite = False
        if not finite:
            shown = repr(v) if len(repr(v)) < 40 else repr(v)[:20] + "..."
            raise InputError(f"{key}: weight of {s!r} is not a finite number: {shown}", source)
        if not lo - 1e-9 <= v <= hi + 1e-9:
            raise InputError(f"{key}: weight {v} of {s!r} is outside the rig's range [{lo:g}, {hi:g}]", source)
        if v != 0:
            out[str(s)] = float(v)
    return region, out


def find_keys_file(poses_path: Path, library: dict) -> Path | None:
    """The KEYS.json the library was fitted from (its ``keys.file``, as given or next to POSES.json)."""
    name = (library.get("keys") or {}).get("file")
    if not name:
        return None
    from keyshape.base.files import found_beside
    return found_beside(name, poses_path.parent)


class PoseHandler(LocalHandler):
    """Request handler; the server object carries the library, the rig and the renderer."""

    server_version = "keyshape-pose"

    page_files = PAGE_FILES
    data_path = "/api/library"

    def get_render(self, key: str) -> None:
        srv = self.server
        if not srv.has_key(key):
            self.send_error_json(HTTPStatus.NOT_FOUND, f"no key {key!r} in the pose library")
        elif srv.renderer is None:
            self.send_error_json(HTTPStatus.NOT_FOUND, "the rig has no faces to render")
        else:
            self.send_body(HTTPStatus.OK, srv.render_png(key), "image/png")

    put_prefix = "/api/poses/"
    put_what = "the pose"
    put_expected = 'expected {"pose": {"shape": weight, ...}}'
    put_refused = "only key poses can be written"

    def put_target(self, key: str):
        if not self.server.has_key(key):
            self.send_error_json(HTTPStatus.NOT_FOUND, f"no key {key!r} in the pose library")
            return NO_BODY
        return key

    def put(self, key: str, body) -> dict:
        try:
            pose = body["pose"]
        except (KeyError, TypeError):
            raise InputError(self.put_expected) from None
        return {"saved": key, "pose": self.server.set_pose(key, pose)}


class PoseServer(LocalServer):
    """The pose-correction server for one POSES.json (see the module docstring).

    Parameters
    ----------
    poses : path of the POSES.json to correct (read and checked against the rig's shapes)
    rig : :class:`~keyshape.retarget.rig.model.Rig`, with its mesh for the rendered preview
    keys : KEYS.json the library came from (default: its ``keys.file`` when that exists);
        gives the actor's key contours shown beside each pose
    port : TCP port on 127.0.0.1 (0: any free port; see :attr:`port`)
    size : side of the rendered rig image in pixels
    """

    def __init__(self, poses: str | Path, rig, keys: str | Path | None = None, port: int = 0, size: int = 320,
                 verbose: bool = False):
        from keyshape.base.formats.poses import read_poses

        self.path = Path(poses).resolve()
        self.library = read_poses(self.path, rig.names)
        self.rig = rig
        self.verbose = verbose
        self.lock = threading.Lock()
        self.actor = self._actor_shapes(keys)
        self.renderer = None
        if rig.mesh is not None and rig.mesh.polygons:
            from keyshape.retarget.output.preview import RigRenderer
            self.renderer = RigRenderer(rig, (size, size)).fit(np.eye(rig.n_shapes))
        super().__init__(port, PoseHandler)

    def _actor_shapes(self, keys) -> dict:
        from keyshape.base.formats.keys import read_keys
        from keyshape.base.schemes import load_scheme
        path = Path(keys) if keys is not None else find_keys_file(self.path, self.library)
        if path is None:
            return {}
        scheme_name, _, regions = read_keys(path)
        scheme = load_scheme(scheme_name)
        out = {}
        for rk in regions:
            rest = rk.rest if rk.rest is not None else rk.neutral
            # the scheme's contours restricted to the region's points, as index pairs into the region
            local = {int(p): i for i, p in enumerate(rk.points)}
            lines = [[local[int(p)] for p in c if int(p) in local] for c in scheme.contours.values()]
            closed = [bool(scheme.closed.get(name, False)) for name in scheme.contours]
            for name, shape in zip(rk.names, rk.keys):
                out[name] = {"rest": np.round(rest, 3).tolist(), "shape": np.round(shape, 3).tolist(),
                             "lines": [ln for ln in lines if len(ln) > 1],
                             "closed": [c for c, ln in zip(closed, lines) if len(ln) > 1]}
        return out

    def has_key(self, key: str) -> bool:
        return any(key in reg["keys"] for reg in self.library["regions"].values())

    def page_data(self) -> dict:
        """What the page needs: the library, the rig range, the actor's key contours."""
        return {"file": self.path.name, "range": self.library.get("range", [0.0, 1.0]),
                "regions": {r: {"shapes": reg["shapes"], "keys": reg["keys"]}
                            for r, reg in self.library["regions"].items()},
                "actor": self.actor, "render": self.renderer is not None}

    def set_pose(self, key: str, pose) -> dict:
        """Replace ``key``'s pose after checking it, and rewrite POSES.json atomically."""
        from keyshape.base.formats.poses import write_poses
        import copy

        from keyshape.base.files import user_save
        region, clean = check_pose(self.library, key, pose, self.path)
        with self.lock:
            library = copy.deepcopy(self.library)
            library["regions"][region]["keys"][key] = clean
            with user_save():
                write_poses(self.path, library)     # an OSError leaves the library what the file holds
            self.library = library
        return clean

    def render_png(self, key: str) -> bytes:
        """The rig in ``key``'s current pose, as PNG bytes."""
        import cv2

        from keyshape.retarget.rig.poses import pose_vector
        with self.lock:
            pose = next(reg["keys"][key] for reg in self.library["regions"].values() if key in reg["keys"])
        img = self.renderer.render(self.rig.evaluate(pose_vector(pose, self.rig.names)[None])[0])
        ok, buf = cv2.imencode(".png", img)
        return buf.tobytes()


def serve(poses: str | Path, rig, keys: str | Path | None = None, port: int = 8766) -> None:
    """Serve the page until Ctrl-C (or SIGTERM); prints the address."""
    server = listen(lambda: PoseServer(poses, rig, keys, port), port)
    print(f"correct the poses at {server.url} (Ctrl-C to stop); every change is saved to {server.path}",
          flush=True)
    serve_until_stopped(server)
