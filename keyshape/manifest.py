"""The project manifest of ``keyshape batch`` (TOML, read with :mod:`tomllib`), checked against its schema.

Design notes and figures: docs/batch.md, "Notes on the code", ``keyshape/manifest.py``.
"""
from __future__ import annotations

import difflib
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from keyshape.base.errors import InputError, require_file
from keyshape.cli import SEED_MAX
from keyshape.decompose import defaults as D
from keyshape.decompose.defaults import METHODS, SOLVERS

OUTPUTS = ("tracks", "weights", "glb", "curves", "livelink", "preview", "usd")
#: file name of each output inside ``OUT_DIR/<actor>/<take>/``
OUTPUT_FILES = {"tracks": "tracks.csv", "weights": "weights.csv", "glb": "animation.glb", "curves": "curves.csv",
                "livelink": "livelink.csv", "preview": "preview.mp4", "usd": "animation.usdc"}
SMOOTHERS = ("none", "savgol", "oneeuro")
REGION_NAMES = ("mouth", "eyes", "pupils")
#: names batch writes inside an actor's folder (a take may not be named one of them) and in OUT_DIR
ACTOR_FILES = ("batch.json", "model.npz", "keys.json")
TOP_FILES = ("report.json",)


@dataclass
class Settings:
    outputs: list[str] = field(default_factory=lambda: ["tracks", "weights", "glb"])
    smooth: str = "none"
    solver: str = D.SOLVER              # the stage's defaults (keyshape.decompose.api), as the commands
    ridge: float = D.RIDGE
    smooth_lambda: float = D.SMOOTH_LAMBDA


@dataclass
class Actor:
    name: str
    video: Path | None = None
    labels: Path | None = None
    model: Path | None = None
    scheme: str = "contours48"
    components: int | None = None
    morphs: int = 120
    seed: int = 0
    keys: int = 8
    selector: str = D.METHOD
    regions: list[str] | None = None
    targets: Path | None = None
    neutral: Path | None = None
    map: Path | None = None
    target_regions: Path | None = None
    rig: Path | None = None
    poses: Path | None = None
    landmarks: Path | None = None
    line: int | None = None


@dataclass
class Take:
    actor: str
    video: Path
    name: str
    start: int = 0
    stop: int | None = None
    line: int | None = None


@dataclass
class Manifest:
    path: Path
    settings: Settings
    actors: dict[str, Actor]
    takes: list[Take]


# key -> (python types, description for errors); paths are str in TOML
_ACTOR = {"video": (str, "a path"), "labels": (str, "a path"), "model": (str, "a path"),
          "scheme": (str, "a scheme name or JSON path"), "components": (int, "an integer"),
          "morphs": (int, "an integer"), "seed": (int, "an integer"), "keys": (int, "an integer"),
          "selector": (str, "a selector name"), "regions": (list, "a list of region names"),
          "targets": (str, "a path"), "neutral": (str, "a path"), "map": (str, "a path"),
          "target_regions": (str, "a path"), "rig": (str, "a path"), "poses": (str, "a path"),
          "landmarks": (str, "a path")}
_TAKE = {"actor": (str, "an actor name"), "video": (str, "a path"), "name": (str, "a name"),
         "frames": (list, "[start, stop]")}
_SETTINGS = {"outputs": (list, "a list of output names"), "smooth": (str, "a smoother name"),
             "solver": (str, "a solver name"), "ridge": ((int, float), "a number"),
             "smooth_lambda": ((int, float), "a number")}
_PATH_KEYS = {"video", "labels", "model", "targets", "neutral", "map", "target_regions", "rig", "poses", "landmarks"}


class _Lines:
    """Line numbers of tables and keys in the manifest text (tomllib gives none)."""

    _HEADER = re.compile(r"^\s*(\[\[?)\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
    _KEY = re.compile(r"^\s*([A-Za-z0-9_\-\"']+)\s*=")

    def __init__(self, text: str):
        self.tables: dict[tuple, int] = {}
        self.keys: dict[tuple, int] = {}
        current: tuple = ()
        n_takes = -1
        for ln, line in enumerate(text.splitlines(), start=1):
            m = self._HEADER.match(line)
            if m:
                parts = tuple(p.strip().strip("\"'") for p in m.group(2).split("."))
                if m.group(1) == "[[":
                    if parts == ("takes",):
                        n_takes += 1
                        parts = ("takes", n_takes)
                current = parts
                self.tables.setdefault(current, ln)
                continue
            m = self._KEY.match(line)
            if m:
                self.keys.setdefault(current + (m.group(1).strip("\"'"),), ln)

    def of(self, *where) -> int | None:
        return self.keys.get(tuple(where)) or self.tables.get(tuple(where)) or \
            (self.tables.get(tuple(where[:-1])) if len(where) > 1 else None)


def _unknown(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1)
    return f"unknown key {key!r}" + (f" (did you mean {close[0]!r}?)" if close else "") + \
        f"; expected one of {', '.join(allowed)}"


def _check_table(table: dict, schema: dict, err, where: tuple) -> None:
    for key, value in table.items():
        if key not in schema:
            err(_unknown(key, schema), *where, key)
        types, what = schema[key]
        if isinstance(value, bool) or not isinstance(value, types):
            err(f"{key!r} must be {what}, got {value!r}", *where, key)


def read_manifest(path: str | Path) -> Manifest:
    """Read and check a manifest; paths come back absolute (relative ones resolved against its folder)."""
    path = require_file(path, "manifest")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text (byte {exc.start}): a manifest is a TOML text file", path) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"at line (\d+)", str(exc))
        raise InputError(f"not valid TOML: {exc}", path, int(m.group(1)) if m else None) from None
    lines = _Lines(text)
    base = path.parent

    def err(message, *where):
        raise InputError(message, path, lines.of(*where))

    for key in data:
        if key not in ("actors", "takes", "settings"):
            err(_unknown(key, ("actors", "takes", "settings")), key)

    raw = data.get("settings", {})
    if not isinstance(raw, dict):
        err("'settings' must be a table [settings]", "settings")
    _check_table(raw, _SETTINGS, err, ("settings",))
    settings = Settings(**{k: (float(v) if k in ("ridge", "smooth_lambda") else v) for k, v in raw.items()})
    bad = [o for o in settings.outputs if not isinstance(o, str) or o not in OUTPUTS]
    if bad:
        err(f"unknown output {bad[0]!r}: expected some of {', '.join(OUTPUTS)}", "settings", "outputs")
    for o in ("tracks", "weights"):      # always written: the batch resumes from them
        if o not in settings.outputs:
            settings.outputs.insert(0, o)
    if settings.smooth not in SMOOTHERS:
        err(f"smooth {settings.smooth!r}: expected one of {', '.join(SMOOTHERS)}", "settings", "smooth")
    if settings.solver not in SOLVERS:
        err(f"solver {settings.solver!r}: expected one of {', '.join(SOLVERS)}", "settings", "solver")
    for key in ("ridge", "smooth_lambda"):
        v = getattr(settings, key)
        if not (math.isfinite(v) and 0 <= v <= 1e6):
            err(f"{key} = {v!r}: must be a finite number from 0 to 1e6", "settings", key)

    actors_raw = data.get("actors")
    if not isinstance(actors_raw, dict) or not actors_raw:
        err("no actors: add a table [actors.NAME] with video and labels (or model)", "actors")
    actors: dict[str, Actor] = {}
    for name, a in actors_raw.items():
        if not isinstance(a, dict):
            err(f"actors.{name} must be a table [actors.{name}]", "actors", name)
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", name) or name in (".", ".."):
            err(f"actor name {name!r}: use letters, digits, '_', '-', '.' (it names a folder)", "actors", name)
        _check_table(a, _ACTOR, err, ("actors", name))
        kw = {k: (base / v if k in _PATH_KEYS else v) for k, v in a.items()}
        actor = Actor(name, line=lines.of("actors", name), **kw)
        if (actor.model is None) == (actor.labels is None):
            err(f"actor {name!r}: give labels (with video) or model, not {'both' if actor.model else 'neither'}",
                "actors", name)
        if actor.labels is not None and actor.video is None:
            err(f"actor {name!r}: labels need the video they belong to ('video = ...')", "actors", name, "labels")
        if actor.selector not in METHODS:
            err(f"selector {actor.selector!r}: expected one of {', '.join(METHODS)}", "actors", name, "selector")
        if actor.keys < 1:
            err(f"keys must be >= 1, got {actor.keys}", "actors", name, "keys")
        for key, lo, hi in (("components", 1, 10_000), ("morphs", 0, 100_000), ("seed", 0, SEED_MAX)):
            v = getattr(actor, key)
            if v is not None and not lo <= v <= hi:
                err(f"{key} = {v}: must be an integer from {lo} to {hi}", "actors", name, key)
        if name in TOP_FILES:
            err(f"actor name {name!r} is a file keyshape batch writes in the output folder: choose another",
                "actors", name)
        if actor.regions is not None and (not actor.regions or any(r not in REGION_NAMES for r in actor.regions)):
            err(f"regions must be some of {', '.join(REGION_NAMES)}, got {actor.regions!r}", "actors", name,
                "regions")
        if actor.targets is not None and actor.rig is not None:
            err(f"actor {name!r}: give targets (one per key) or a rig, not both", "actors", name, "rig")
        if actor.targets is None and any(k in a for k in ("map", "target_regions")):
            err(f"actor {name!r}: map and target_regions need targets", "actors", name)
        if actor.targets is None and actor.rig is None and "neutral" in a:
            err(f"actor {name!r}: neutral needs targets or a rig", "actors", name, "neutral")
        if actor.rig is None and any(k in a for k in ("poses", "landmarks")):
            err(f"actor {name!r}: poses and landmarks need a rig", "actors", name)
        actors[name] = actor

    takes_raw = data.get("takes")
    if not isinstance(takes_raw, list) or not takes_raw:
        err("no takes: add [[takes]] tables with actor and video", "takes")
    takes: list[Take] = []
    seen: dict[tuple, int] = {}
    for i, t in enumerate(takes_raw):
        if not isinstance(t, dict):
            err(f"take {i + 1} is {t!r}: each take must be a table [[takes]] with actor and video", "takes")
        _check_table(t, _TAKE, err, ("takes", i))
        for key in ("actor", "video"):
            if key not in t:
                err(f"take {i + 1} has no {key!r}", "takes", i)
        if t["actor"] not in actors:
            err(f"unknown actor {t['actor']!r}: the manifest has {', '.join(actors)}", "takes", i, "actor")
        video = base / t["video"]
        name = t.get("name", video.stem)
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", name) or name in (".", ".."):
            err(f"take name {name!r}: use letters, digits, '_', '-', '.' (it names a folder)", "takes", i,
                "name" if "name" in t else "video")
        if name in ACTOR_FILES:
            err(f"take name {name!r} is a file keyshape batch writes in the actor's folder: give the take "
                "another 'name'", "takes", i, "name" if "name" in t else "video")
        start, stop = 0, None
        if "frames" in t:
            fr = t["frames"]
            if len(fr) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in fr) \
                    or not 0 <= fr[0] < fr[1]:
                err(f"frames must be [start, stop] with 0 <= start < stop, got {fr!r}", "takes", i, "frames")
            start, stop = fr
        key = (t["actor"], name)
        if key in seen:
            err(f"take {name!r} of actor {t['actor']!r} is already line {seen[key]}: outputs would collide "
                f"(give one a 'name')", "takes", i)
        seen[key] = lines.of("takes", i) or 0
        takes.append(Take(t["actor"], video, name, start, stop, lines.of("takes", i)))
    return Manifest(path, settings, actors, takes)
