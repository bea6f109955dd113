"""KEYS.json: key shapes per region (:class:`RegionKeys`); reader and writer.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/keys.py``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import read_json, write_json

FORMAT = "keyshape-keys"
#: face regions (section 5 of the paper) and the scheme regions they are built from
REGIONS = {"mouth": "mouth", "eyes": "eyes+brows", "pupils": "pupils"}


@dataclass
class RegionKeys:
    """Key shapes of one region (model frame).

    Attributes
    ----------
    region : str
    method : str
    points : (n,) point indices of the region in the scheme
    frames : (n_keys,) video frame numbers of the key frames (``tracks.frame``)
    keys : (n_keys, n, 2) key shapes
    neutral : (n, 2) the shape weights are relative to (the take's mean, or the actor's neutral frame)
    from_frame : (n_keys,) bool, False for keys that are cluster means rather than frames
    rest : (n, 2) or None, the actor's neutral (most relaxed) shape of the region, what a rig
        pose's motion is measured from (``keyshape pose``)
    rest_frame : int or None, the video frame ``rest`` was taken from
    takes : (n_keys,) int or None, for keys chosen from several tracks files: which file
        (index into KEYS.json's ``source.tracks``) each key's frame is in
    """

    region: str
    method: str
    points: np.ndarray
    frames: np.ndarray
    keys: np.ndarray
    neutral: np.ndarray
    from_frame: np.ndarray = field(default=None)
    rest: np.ndarray | None = None
    rest_frame: int | None = None
    takes: np.ndarray | None = None

    def __post_init__(self):
        if self.from_frame is None:
            self.from_frame = np.ones(len(self.frames), dtype=bool)

    @property
    def names(self) -> list[str]:
        return [f"{self.region}_{i}" for i in range(len(self.keys))]


def write_keys(path: str | Path, scheme_name: str, n_points: int, regions: list[RegionKeys],
               source: dict | None = None, head_pose: dict | None = None) -> None:
    """Write key shapes of one or more regions to a KEYS.json file, atomically.

    ``source``: where the keys came from, ``{"model": "sha256:...", "scheme": ..., "tracks": [files]}``
    (``keyshape decompose`` refuses keys of another model). ``head_pose``: how the head was taken
    out of the shapes (the module docstring; default: not recorded, the tracker's pose)."""
    data = {"format": FORMAT, "version": 1, "scheme": scheme_name, "n_points": int(n_points),
            "coordinates": "model frame (head pose removed)", "regions": {}}
    if source:
        data["source"] = source
    if head_pose:
        data["head_pose"] = head_pose
    for rk in regions:
        data["regions"][rk.region] = {
            "method": rk.method, "points": [int(i) for i in rk.points],
            "neutral": np.round(rk.neutral, 6).tolist(),
            "keys": [{"name": name, "frame": int(f), "from_frame": bool(ff), "shape": np.round(s, 6).tolist()}
                     for name, f, ff, s in zip(rk.names, rk.frames, rk.from_frame, rk.keys)]}
        if rk.rest is not None:
            data["regions"][rk.region]["rest"] = np.round(rk.rest, 6).tolist()
            data["regions"][rk.region]["rest_frame"] = int(rk.rest_frame)
        if rk.takes is not None:
            for k, t in zip(data["regions"][rk.region]["keys"], rk.takes):
                k["take"] = int(t)
    write_json(path, data, end="\n")


def read_keys(path: str | Path) -> tuple[str, int, list[RegionKeys]]:
    """Read a KEYS.json file: (scheme name, n_points, [RegionKeys, ...]); errors name the file."""
    path = require_file(path, "key-shapes file")
    data = read_json(path, "key-shapes file")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"not a key-shapes file: expected \"format\": \"{FORMAT}\" "
                         f"(write one with 'keyshape select')", path)
    try:
        scheme, n_points = str(data["scheme"]), int(data["n_points"])
        out = []
        for region, r in data["regions"].items():
            if region not in REGIONS:
                raise InputError(f"unknown region {region!r}: expected one of {', '.join(REGIONS)}", path)
            pts = np.array(r["points"], dtype=np.intp)
            neutral = np.array(r["neutral"], dtype=np.float64)
            keys = np.array([k["shape"] for k in r["keys"]], dtype=np.float64)
            frames = np.array([k["frame"] for k in r["keys"]], dtype=np.int64)
            ff = np.array([k.get("from_frame", True) for k in r["keys"]], dtype=bool)
            if not len(keys):
                raise InputError(f"region {region!r} has no key shapes", path)
            if neutral.shape != (len(pts), 2) or keys.shape != (len(keys), len(pts), 2):
                raise InputError(f"region {region!r}: {len(pts)} points, but neutral has shape {neutral.shape} "
                                 f"and keys {keys.shape}", path)
            if (pts < 0).any() or (pts >= n_points).any():
                raise InputError(f"region {region!r} names points outside 0..{n_points - 1}", path)
            names = [k.get("name") for k in r["keys"]]
            expected = [f"{region}_{i}" for i in range(len(keys))]
            if names != expected:
                raise InputError(f"region {region!r}: key names must be {expected[0]}..{expected[-1]} in "
                                 f"order, got {names[:3]}...", path)
            if not (np.isfinite(keys).all() and np.isfinite(neutral).all()):
                raise InputError(f"region {region!r}: non-finite coordinates", path)
            if np.abs(keys).max() > 1e5 or np.abs(neutral).max() > 1e5:
                raise InputError(f"region {region!r}: implausible coordinates (beyond 1e5 pixels)", path)
            if len(np.unique(pts)) != len(pts):
                raise InputError(f"region {region!r} names a point twice", path)
            rest = np.array(r["rest"], dtype=np.float64) if "rest" in r else None
            if rest is not None and (rest.shape != (len(pts), 2) or not np.isfinite(rest).all()
                                     or np.abs(rest).max() > 1e5):
                raise InputError(f"region {region!r}: rest must be {len(pts)} finite points", path)
            rest_frame = int(r["rest_frame"]) if "rest_frame" in r else None
            takes = [k.get("take") for k in r["keys"]]
            takes = None if any(t is None for t in takes) else np.array([int(t) for t in takes])
            out.append(RegionKeys(region, str(r.get("method", "")), pts, frames, keys, neutral, ff,
                                  rest, rest_frame, takes))
            if len({rk.region for rk in out}) != len(out):
                raise InputError(f"region {region!r} twice", path)
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"malformed key-shapes file (missing or bad field: {exc})", path) from None
    if not out:
        raise InputError("no regions in key-shapes file", path)
    return scheme, n_points, out


def read_keys_source(path: str | Path) -> dict:
    """The ``source`` of a KEYS.json file (``{}`` when it has none): model, scheme and tracks files."""
    path = require_file(path, "key-shapes file")
    try:
        data = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None
    src = data.get("source", {}) if isinstance(data, dict) else {}
    return src if isinstance(src, dict) else {}


def check_keys_model(path: str | Path, model: str | None, allow: bool = False, what: str = "these tracks") -> None:
    """Refuse a key set chosen from tracks of another tracker model than ``model`` (a fingerprint,
    ``sha256:...``; None: unknown, not checked) unless ``allow`` (``--allow-foreign-keys``): keys belong
    to one actor's model, and another model's points mean other things. One line naming the key set."""
    mk = read_keys_source(path).get("model")
    if mk and model and mk != model and not allow:
        raise InputError(f"these keys were chosen from tracks of another tracker model ({mk}; {what}: {model}): "
                         "keys belong to one actor's model. Select keys from this model's tracks, or pass "
                         "--allow-foreign-keys", path)


def read_keys_head_pose(path: str | Path) -> dict:
    """The ``head_pose`` of a KEYS.json file, checked (``{"method": "tracker"}`` when it has none)."""
    path = require_file(path, "key-shapes file")
    data = read_json(path, "key-shapes file")
    hp = data.get("head_pose") if isinstance(data, dict) else None
    if hp is None:
        return {"method": "tracker"}
    try:
        method = hp["method"]
        if method == "tracker":
            return {"method": "tracker"}
        if method == "3d":
            return _head_pose_3d(hp, int(data.get("n_points", 0)), path)
        if method != "rigid":
            raise InputError(f"head_pose method {method!r}: expected 'rigid' or 'tracker' (2D) or '3d'", path)
        pts = [int(i) for i in hp["points"]]
        ref = np.asarray(hp["reference"], dtype=np.float64)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"malformed head_pose (missing or bad field: {exc})", path) from None
    n = int(data.get("n_points", 0))
    if len(pts) < 2 or len(set(pts)) != len(pts) or not all(0 <= i < n for i in pts):
        raise InputError(f"head_pose points {pts}: need two or more distinct points in 0..{n - 1}", path)
    if ref.shape != (len(pts), 2) or not np.isfinite(ref).all() or np.abs(ref).max() > 1e5:
        raise InputError(f"head_pose reference must be {len(pts)} finite points", path)
    if np.linalg.norm(ref - ref.mean(axis=0)) < 1e-9:
        raise InputError("head_pose reference points coincide", path)
    return {"method": "rigid", "points": pts, "reference": ref.tolist()}


def _head_pose_3d(hp: dict, n: int, path) -> dict:
    """A checked ``{"method": "3d", ...}`` head_pose entry (:class:`keyshape.decompose.head3d.HeadPose3D`)."""
    try:
        pts = [int(i) for i in hp["points"]]
        arr = {k: np.asarray(hp[k], dtype=np.float64) for k in ("generic", "template", "weights", "centre", "zero", "frame")}
        scal = {k: float(hp[k]) for k in ("distance", "smooth", "focal", "spread", "robust")}
        adapt, zf, anchor = bool(hp["adapt"]), int(hp["zero_frame"]), bool(hp["anchor"])
        rounds = int(hp["robust_rounds"])
        ref = np.asarray(hp["reference"], dtype=np.float64)
        eyes = [int(i) for i in hp.get("eyeballs", [])]           # optional (older files: none)
        eye_radius = float(hp.get("eye_radius", 1.2))
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"malformed head_pose (missing or bad field: {exc})", path) from None
    if arr["generic"].ndim == 2 and len(arr["generic"]) > n:
        n = len(arr["generic"])          # the scheme's points and its auxiliary ones after them (the nose)
    shapes = {"generic": (n, 3), "template": (n, 3), "weights": (n,), "centre": (2,), "zero": (3, 3), "frame": (3,)}
    for k, shp in shapes.items():
        if arr[k].shape != shp or not np.isfinite(arr[k]).all() or np.abs(arr[k]).max() > 1e6:
            raise InputError(f"head_pose {k} must be {shp} finite numbers", path)
    if len(pts) < 2 or len(set(pts)) != len(pts) or not all(0 <= i < n for i in pts):
        raise InputError(f"head_pose points {pts}: need two or more distinct points in 0..{n - 1}", path)
    if not (np.isfinite(list(scal.values())).all() and scal["focal"] > 0 and scal["distance"] > 0
            and min(scal["smooth"], scal["spread"], scal["robust"]) >= 0 and 0 <= rounds <= 20):
        raise InputError("head_pose focal and distance must be > 0, smooth, spread and robust >= 0, "
                         "robust_rounds 0..20", path)
    if (arr["weights"] < 0).any() or (arr["weights"][pts] <= 0).any() or arr["frame"][0] <= 0:
        raise InputError("head_pose weights must be >= 0 (> 0 on its points) and its frame's scale > 0", path)
    if np.abs(arr["zero"] @ arr["zero"].T - np.eye(3)).max() > 1e-3:
        raise InputError("head_pose zero is not a rotation", path)
    if ref.shape != (len(pts), 2) or not np.isfinite(ref).all() or np.linalg.norm(ref - ref.mean(0)) < 1e-9:
        raise InputError(f"head_pose reference must be {len(pts)} distinct finite points", path)
    if not all(0 <= i < n for i in eyes) or not (np.isfinite(eye_radius) and eye_radius > 0):
        raise InputError(f"head_pose eyeballs {eyes} must be points in 0..{n - 1}, eye_radius > 0", path)
    return {"method": "3d", "points": pts, **scal, "adapt": adapt, "zero_frame": zf, "anchor": anchor,
            "robust_rounds": rounds, "eyeballs": eyes, "eye_radius": eye_radius,
            "reference": ref.tolist(),
            **{k: v.tolist() for k, v in arr.items()}}
