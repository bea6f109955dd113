"""Landmark schemes as data: which points exist, which contours and face regions they form.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/schemes/__init__.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import re
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, MissingFileError
from keyshape.base.files import read_json

_HERE = Path(__file__).parent
BUILTIN = ("contours48", "ibug68")
#: name of an auxiliary point group (the prefix of its tracks columns, ``nose_x_0..``)
AUX_NAME = r"[a-z][a-z0-9]*"
DEFAULT = "contours48"


@dataclass(frozen=True)
class Scheme:
    """A landmark scheme (read-only).

    Attributes
    ----------
    name : str
    n_points : int
    contours : dict[str, tuple[int, ...]]
        Point indices of each contour, in drawing order.
    closed : dict[str, bool]
        Whether each contour is a closed loop.
    regions : dict[str, tuple[int, ...]]
        Point indices of each face region (``mouth``, ``eyes``, ...).
    inter_ocular : tuple[int, int]
        Outer eye corners; their distance normalises errors (NME).
    description : str
    rigid : tuple[int, ...]
        Points rigid with the skull (eye corners, nose bridge); empty when the scheme names none.
    corners : dict[str, tuple[int, int]]
        The two corners of the closed contours that name them (eyes, lips): a contour's
        opening is measured across the line between them.
    auxiliary : dict[str, tuple[int, ...]]
        Named groups of auxiliary points rigid with the skull (the nose) and the iBUG-68 point each
        one is; not among ``n_points`` unless the scheme is a :meth:`full` one.
    n_core : int
        In a :meth:`full` scheme, how many of its points are the base scheme's (the auxiliary groups
        follow them in order); 0 in a base scheme.
    """

    name: str
    n_points: int
    contours: dict
    closed: dict
    regions: dict
    inter_ocular: tuple
    description: str = ""
    source: str = field(default="", compare=False)
    rigid: tuple = ()
    corners: dict = field(default_factory=dict, compare=False)
    auxiliary: dict = field(default_factory=dict)
    n_core: int = 0

    @property
    def core(self) -> int:
        """Number of the base scheme's own points (``n_points`` in a base scheme)."""
        return self.n_core or self.n_points

    @property
    def base_name(self) -> str:
        """The base scheme's name (``contours48`` of ``contours48+nose``)."""
        return self.name.split("+")[0] if self.n_core else self.name

    @property
    def auxiliary_sources(self) -> list[int]:
        """The iBUG-68 source point of each auxiliary point, all groups in order."""
        return [i for src in self.auxiliary.values() for i in src]

    def full(self) -> "Scheme":
        """The scheme with its auxiliary groups appended as points (each an open contour and a region),
        named ``NAME+GROUP``; ``self`` where it has none or is already full. ``rigid`` stays the base
        scheme's: the 3D head pose weighs the auxiliary points through its template's weights
        (:func:`load_head_template`), and the head frame stays anchored on the eye corners (anchored on
        the nose too, an error in the nose tip's depth read as a sideways slide of the whole face)."""
        if not self.auxiliary or self.n_core:
            return self
        n, contours, closed, regions = self.n_points, dict(self.contours), dict(self.closed), dict(self.regions)
        for g, src in self.auxiliary.items():
            idx = tuple(range(n, n + len(src)))
            contours[g], closed[g], regions[g] = idx, False, idx
            n += len(src)
        return replace(self, name="+".join([self.name, *self.auxiliary]), n_points=n, contours=contours,
                       closed=closed, regions=regions, n_core=self.n_points)

    def split(self, points: np.ndarray) -> tuple[np.ndarray, dict]:
        """A :meth:`full` scheme's ``points`` (..., n_points, 2) -> (the base scheme's (..., core, 2),
        {group: (..., k, 2)}); a base scheme's -> (``points``, {})."""
        if not self.n_core:
            return points, {}
        out, i = {}, self.n_core
        for g, src in self.auxiliary.items():
            out[g] = points[..., i:i + len(src), :]
            i += len(src)
        return points[..., :self.n_core, :], out

    def region(self, name: str) -> np.ndarray:
        """Point indices of region ``name`` (``+``-joined names give the union, e.g. ``eyes+brows``)."""
        idx: list[int] = []
        for part in name.split("+"):
            if part not in self.regions:
                raise InputError(f"scheme {self.name!r} has no region {part!r}; "
                                 f"it has {', '.join(self.regions)}")
            idx.extend(self.regions[part])
        return np.array(sorted(set(idx)), dtype=np.intp)

    def interocular_distance(self, shapes: np.ndarray) -> np.ndarray:
        """Distance between the outer eye corners of ``shapes`` (..., n_points, 2) -> (...)."""
        a, b = self.inter_ocular
        return np.linalg.norm(shapes[..., a, :] - shapes[..., b, :], axis=-1)

    def check_shapes(self, shapes: np.ndarray, what: str = "shapes") -> np.ndarray:
        """Return ``shapes`` as float64 after checking its last two axes are (n_points, 2)."""
        arr = np.asarray(shapes, dtype=np.float64)
        if arr.ndim < 2 or arr.shape[-2:] != (self.n_points, 2):
            raise InputError(f"{what}: expected shape (..., {self.n_points}, 2) for scheme "
                             f"{self.name!r}, got {arr.shape}")
        return arr


def scheme_to_dict(s: Scheme) -> dict:
    """``s`` in the layout of a scheme JSON file (what :func:`scheme_from_dict` reads)."""
    return {"name": s.name, "n_points": s.n_points, "description": s.description,
            "contours": {k: {"points": list(v), "closed": s.closed[k],
                             **({"corners": list(s.corners[k])} if k in s.corners else {})}
                         for k, v in s.contours.items()},
            "regions": {k: list(v) for k, v in s.regions.items()}, "inter_ocular": list(s.inter_ocular),
            **({"rigid": list(s.rigid)} if s.rigid else {}),
            **({"auxiliary": {k: {"ibug68": list(v)} for k, v in s.auxiliary.items()}} if s.auxiliary else {}),
            **({"n_core": s.n_core} if s.n_core else {})}


def scheme_from_dict(data: dict, source: str) -> Scheme:
    """Check a scheme JSON object and build the :class:`Scheme`; errors name ``source``."""
    try:
        n = int(data["n_points"])
        contours = {k: tuple(int(i) for i in v["points"]) for k, v in data["contours"].items()}
        closed = {k: bool(v.get("closed", False)) for k, v in data["contours"].items()}
        regions = {k: tuple(int(i) for i in v) for k, v in data["regions"].items()}
        io = tuple(int(i) for i in data["inter_ocular"])
        rigid = tuple(int(i) for i in data.get("rigid", ()))
        corners = {k: tuple(int(i) for i in v["corners"]) for k, v in data["contours"].items() if "corners" in v}
        auxiliary = {str(k): tuple(int(i) for i in v["ibug68"]) for k, v in data.get("auxiliary", {}).items()}
        n_core = int(data.get("n_core", 0))
        name = str(data["name"])
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
        raise InputError(f"not a landmark scheme (missing or bad field: {exc})", source) from None
    if not 1 <= n <= 100000:
        raise InputError(f"n_points {n}: expected 1 to 100000", source)
    for kind, groups in (("contour", contours), ("region", regions)):
        for k, idx in groups.items():
            bad = [i for i in idx if not 0 <= i < n]
            if bad:
                raise InputError(f"{kind} {k!r} names points {bad} outside 0..{n - 1}", source)
    if len(io) != 2 or not all(0 <= i < n for i in io) or io[0] == io[1]:
        raise InputError(f"inter_ocular must be two distinct point indices in 0..{n - 1}, got {io}", source)
    if rigid and (len(set(rigid)) != len(rigid) or len(rigid) < 2 or not all(0 <= i < n for i in rigid)):
        raise InputError(f"rigid must be two or more distinct point indices in 0..{n - 1}, got {list(rigid)}", source)
    for k, c in corners.items():
        if len(c) != 2 or c[0] == c[1] or not set(c) <= set(contours[k]):
            raise InputError(f"contour {k!r}: corners must be two distinct points of the contour, got {list(c)}",
                             source)
    for k, src in auxiliary.items():
        if not src or not all(0 <= i < 68 for i in src) or not re.fullmatch(AUX_NAME, k):
            raise InputError(f"auxiliary group {k!r}: expected a lower-case name and one or more iBUG-68 "
                             f"points (0..67), got {list(src)}", source)
    if n_core and n_core + sum(len(v) for v in auxiliary.values()) != n:
        raise InputError(f"n_core {n_core} and the auxiliary points do not add up to n_points {n}", source)
    return Scheme(name, n, contours, closed, regions, io, str(data.get("description", "")), source, rigid, corners,
                  auxiliary, n_core)


def load_scheme(name_or_path: str | Path = DEFAULT) -> Scheme:
    """Load a built-in scheme by name (``contours48``, ``ibug68``) or a scheme JSON file; a built-in
    name followed by its auxiliary groups (``contours48+nose``) is its :meth:`Scheme.full` scheme."""
    s = str(name_or_path)
    base, *groups = s.split("+")
    if groups and (base in BUILTIN or Path(base).is_file()):
        sch = load_scheme(base)
        if list(sch.auxiliary) != groups:
            raise InputError(f"unknown landmark scheme {s!r}: {base} has the auxiliary points "
                             f"{'+'.join(sch.auxiliary) or '(none)'}")
        return sch.full()
    path = _HERE / f"{s}.json" if s in BUILTIN else Path(s)
    if not path.is_file():
        if s in BUILTIN or s.endswith(".json") or "/" in s:
            raise MissingFileError(path, "landmark scheme")
        raise InputError(f"unknown landmark scheme {s!r}: use one of {', '.join(BUILTIN)} or a JSON file")
    return scheme_from_dict(read_json(path, "landmark scheme"), str(path))


def scheme_for_n_points(n_points: int) -> Scheme:
    """The built-in scheme with ``n_points`` points."""
    for name in BUILTIN:
        sch = load_scheme(name)
        if sch.n_points == n_points:
            return sch
    raise InputError(f"no built-in landmark scheme has {n_points} points "
                     f"(contours48 has 48, ibug68 has 68)")


def load_head_template(scheme: Scheme | str) -> tuple[np.ndarray, np.ndarray]:
    """The scheme's points on a generic 3D face and their weights in a head pose fit.

    Returns ``points`` (n_points, 3) cm, head axes (x the actor's left, y up, z out of the face):
    ICT-FaceKit's generic neutral at keyshape's rig landmark correspondence, and ``weights``
    (n_points,): 1 for the points rigid with the skull, less for those expression moves, 0 for
    pupils, mouth corners, lower lip and jaw (``head3d.json``, package data; its ``weights_note``).
    A :meth:`Scheme.full` scheme's auxiliary points are the ``ibug68`` template's at their iBUG-68
    source points, with those points' weights. Raises :class:`InputError` for a scheme without one."""
    if isinstance(scheme, str) and "+" in scheme:
        scheme = load_scheme(scheme)
    full = isinstance(scheme, Scheme) and scheme.n_core
    name = scheme if isinstance(scheme, str) else scheme.base_name
    data = read_json(_HERE / "head3d.json", "3D head template")
    pts = data.get("schemes", {}).get(name)
    if pts is None:
        raise InputError(f"no 3D head template for scheme {name!r} (there is one for "
                         f"{', '.join(data.get('schemes', {}))}): use --head-pose rigid")
    X, w = np.asarray(pts, dtype=np.float64), np.asarray(data["weights"][name], dtype=np.float64)
    if full:
        src = scheme.auxiliary_sources
        X = np.concatenate([X, np.asarray(data["schemes"]["ibug68"], np.float64)[src]])
        w = np.concatenate([w, np.asarray(data["weights"]["ibug68"], np.float64)[src]])
    return X, w
