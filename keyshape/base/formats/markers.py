"""Marker files: C3D (ezc3d), TRC (OpenSim layout) and CSV; one result type, :class:`Markers`.

Conventions
-----------
* ``positions`` is ``(n_frames, n_markers, 3)`` float64 in the file's own axes and
  units (``units``: ``"mm"``, ``"cm"``, ``"m"``); nothing is rotated or rescaled.
* A gap (occluded marker) is NaN, never zeros: C3D points with a negative residual
  and points written as exactly ``(0, 0, 0)`` (the way several systems mark gaps) become
  NaN; empty TRC/CSV fields become NaN.
* C3D labels come from ``POINT:LABELS`` then ``LABELS2``, ``LABELS3``... (systems spill
  past 255 labels there); a point with no label, or an empty label, is named
  ``M001``, ``M002``... by its one-based index. Duplicate labels are an error naming
  them, unless ``duplicates="rename"`` (then the second ``X`` becomes ``X#2``).
* Frame counts come from the data, not ``POINT:FRAMES`` (an INT16 that overflows in
  long takes).

CSV layout (read and written): a header ``frame,time,<label>_x,<label>_y,<label>_z,...``
and optional first comment lines ``# rate=120`` and ``# units=mm``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path, atomic_write


@dataclass
class Markers:
    """A marker take.

    Attributes
    ----------
    positions : (n_frames, n_markers, 3) float64, NaN in gaps
    labels : list of str, one per marker, unique
    rate : float, frames per second
    units : str, e.g. ``"mm"``
    """

    positions: np.ndarray
    labels: list
    rate: float
    units: str = "mm"

    def __post_init__(self):
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.labels = [str(s) for s in self.labels]
        if self.positions.ndim != 3 or self.positions.shape[2] != 3:
            raise InputError(f"positions: expected shape (n_frames, n_markers, 3), got {self.positions.shape}")
        if len(self.labels) != self.positions.shape[1]:
            raise InputError(f"labels: expected {self.positions.shape[1]} labels, got {len(self.labels)}")
        dup = _duplicates(self.labels)
        if dup:
            raise InputError(f"labels: duplicate marker labels {dup}")

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_markers(self) -> int:
        return self.positions.shape[1]

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.rate

    def index(self, names) -> np.ndarray:
        """Indices of ``names`` (case-sensitive first, then case-insensitive); InputError naming unknown ones."""
        lower = {s.lower(): i for i, s in enumerate(self.labels)}
        exact = {s: i for i, s in enumerate(self.labels)}
        out, unknown = [], []
        for n in names:
            i = exact.get(n, lower.get(str(n).lower()))
            (unknown.append(n) if i is None else out.append(i))
        if unknown:
            raise InputError(f"unknown marker label(s) {unknown}; the take has {', '.join(self.labels)}")
        return np.asarray(out, dtype=np.intp)

    def select(self, names) -> "Markers":
        idx = self.index(names)
        return Markers(self.positions[:, idx], [self.labels[i] for i in idx], self.rate, self.units)

    def scaled_to(self, units: str) -> "Markers":
        """The same take in other length units (mm, cm, m)."""
        return Markers(self.positions * unit_scale(self.units, units), self.labels, self.rate, units)


_SCALE = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "in": 0.0254}


def unit_scale(src: str, dst: str) -> float:
    """Factor taking lengths in ``src`` units to ``dst`` units."""
    s, d = str(src).strip().lower(), str(dst).strip().lower()
    if s not in _SCALE or d not in _SCALE:
        raise InputError(f"units: expected one of {', '.join(_SCALE)}, got {src!r} -> {dst!r}")
    return _SCALE[s] / _SCALE[d]


def _duplicates(labels) -> list:
    seen, dup = set(), []
    for s in labels:
        if s in seen and s not in dup:
            dup.append(s)
        seen.add(s)
    return dup


def _fix_labels(labels: list, n: int, path, duplicates: str) -> list:
    labels = [str(s).strip() for s in labels[:n]]
    labels += [""] * (n - len(labels))
    labels = [s if s else f"M{i + 1:03d}" for i, s in enumerate(labels)]
    dup = _duplicates(labels)
    if dup:
        if duplicates != "rename":
            raise InputError(f"duplicate marker labels {dup}: rename them in the file or read with "
                             "duplicates='rename'", path)
        count: dict = {}
        out = []
        for s in labels:
            count[s] = count.get(s, 0) + 1
            out.append(s if count[s] == 1 else f"{s}#{count[s]}")
        labels = out
    return labels


def _gaps_to_nan(p: np.ndarray) -> np.ndarray:
    p = p.copy()
    p[np.all(p == 0.0, axis=-1)] = np.nan
    return p


# ---------------------------------------------------------------------------------------- C3D
def read_c3d(path, duplicates: str = "error") -> Markers:
    """Read the 3D points of a C3D file (analogs are ignored)."""
    import ezc3d

    path = require_file(path, "C3D file")
    try:
        c = ezc3d.c3d(str(path))
    except Exception as exc:  # ezc3d raises bare RuntimeError/IOError
        raise InputError(f"not a readable C3D file ({exc})", path) from None
    params = c["parameters"]["POINT"]
    pts = np.asarray(c["data"]["points"], dtype=np.float64)  # (4, n_markers, n_frames)
    n = pts.shape[1]
    if n == 0:
        raise InputError("the C3D file holds no 3D points", path)
    labels = list(params.get("LABELS", {}).get("value", []))
    k = 2
    while f"LABELS{k}" in params:
        labels += list(params[f"LABELS{k}"]["value"])
        k += 1
    labels = _fix_labels(labels, n, path, duplicates)
    xyz = pts[:3].transpose(2, 1, 0)
    meta = c["data"].get("meta_points", {})
    if "residuals" in meta:
        res = np.asarray(meta["residuals"])[0].T
        xyz[res < 0] = np.nan
    xyz = _gaps_to_nan(xyz)
    rate = float(np.ravel(params.get("RATE", {}).get("value", [c["header"]["points"]["frame_rate"]]))[0])
    units = params.get("UNITS", {}).get("value", ["mm"])
    units = (units[0] if len(units) else "mm").strip() or "mm"
    if not rate > 0:
        raise InputError(f"POINT:RATE is {rate}: expected a positive frame rate", path)
    return Markers(xyz, labels, rate, units)


def write_c3d(path, markers: Markers) -> None:
    """Write ``markers`` as a C3D file (points only; gaps as residual -1), atomically."""
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(markers.rate)]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(markers.labels)
    c.add_parameter("POINT", "UNITS", [markers.units])
    p = np.ones((4, markers.n_markers, markers.n_frames))
    xyz = markers.positions.transpose(2, 1, 0)
    gap = ~np.isfinite(xyz).all(axis=0)
    p[:3] = np.where(gap[None], 0.0, xyz)
    c["data"]["points"] = p
    res = np.where(gap, -1.0, 0.0)[None]
    c["data"]["meta_points"] = {"residuals": res, "camera_masks": np.zeros((7,) + gap.shape, dtype=bool)}
    with atomic_path(path) as tmp:
        c.write(str(tmp))


# ---------------------------------------------------------------------------------------- TRC
def read_trc(path, duplicates: str = "error") -> Markers:
    """Read an OpenSim TRC file (tab- or comma-separated); empty fields are gaps (NaN)."""
    path = require_file(path, "TRC file")
    lines = path.read_text(errors="replace").splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise InputError("not a TRC file: the first line must start with 'PathFileType'", path, 1)
    sep = "\t" if "\t" in lines[1] else ","
    keys = [s.strip() for s in lines[1].split(sep)]
    vals = [s.strip() for s in lines[2].split(sep)]
    head = dict(zip(keys, vals))
    try:
        rate = float(head.get("DataRate") or head["CameraRate"])
        n_markers = int(head["NumMarkers"])
    except (KeyError, ValueError):
        raise InputError("header needs DataRate and NumMarkers values", path, 3) from None
    units = head.get("Units", "mm") or "mm"
    cells = [s.strip() for s in lines[3].split(sep)[2:]]
    names = [cells[3 * k] if 3 * k < len(cells) else "" for k in range(n_markers)]   # X column of each
    packed = [s for s in cells if s]
    if "" in names and len(packed) == n_markers:
        names = packed                          # labels not on the X/Y/Z grid but one per marker
    labels = _fix_labels(names, n_markers, path, duplicates)
    rows, row_ln = [], []
    for ln in range(5, len(lines)):
        line = lines[ln]
        if not line.strip() or not line.split(sep)[0].strip():
            continue
        rows.append(line)
        row_ln.append(ln + 1)
    if not rows:
        raise InputError("no data rows", path)
    width = 2 + 3 * n_markers
    data = np.full((len(rows), width), np.nan)
    for r, (line, ln) in enumerate(zip(rows, row_ln)):
        parts = line.split(sep)[:width]
        try:
            data[r, :len(parts)] = [float(s) if s.strip() else np.nan for s in parts]
        except ValueError:
            raise InputError(f"broken data row: expected {width} numbers (Frame#, Time, X/Y/Z per marker)",
                             path, ln) from None
    xyz = _gaps_to_nan(data[:, 2:].reshape(len(rows), n_markers, 3))
    return Markers(xyz, labels, rate, units)


def _fmt(a: np.ndarray) -> np.ndarray:
    out = np.char.mod("%.6f", a)
    out[~np.isfinite(a)] = ""
    return out


def write_trc(path, markers: Markers) -> None:
    """Write an OpenSim TRC file (tab-separated, gaps as empty fields), atomically."""
    path = Path(path)
    nf, nm = markers.n_frames, markers.n_markers
    lines = [f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
             "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
             f"{markers.rate:g}\t{markers.rate:g}\t{nf}\t{nm}\t{markers.units}\t{markers.rate:g}\t1\t{nf}",
             "Frame#\tTime\t" + "\t".join(f"{s}\t\t" for s in markers.labels).rstrip("\t"),
             "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(nm)),
             ""]
    cells = _fmt(markers.positions.reshape(nf, -1))
    frame = np.arange(1, nf + 1).astype(str)
    time = np.char.mod("%.6f", markers.times)
    body = ["\t".join([f, t, *row]) for f, t, row in zip(frame, time, cells)]
    with atomic_write(path) as f:
        f.write("\n".join(lines + body) + "\n")


# ---------------------------------------------------------------------------------------- CSV
def write_csv(path, markers: Markers) -> None:
    """Write ``frame,time,<label>_x,...`` with ``# rate=`` and ``# units=`` comment lines, atomically."""
    nf = markers.n_frames
    head = "frame,time," + ",".join(f"{s}_{a}" for s in markers.labels for a in "xyz")
    cells = _fmt(markers.positions.reshape(nf, -1))
    body = [",".join([str(i), f"{t:.6f}", *row]) for i, (t, row) in enumerate(zip(markers.times, cells))]
    with atomic_write(path) as f:
        f.write(f"# rate={markers.rate:g}\n# units={markers.units}\n{head}\n" + "\n".join(body) + "\n")


def read_csv(path, rate: float | None = None, units: str | None = None, duplicates: str = "error") -> Markers:
    """Read the CSV layout written by :func:`write_csv` (``rate`` from a comment or the time column)."""
    path = require_file(path, "CSV file")
    lines = path.read_text(errors="replace").splitlines()
    meta, start = {}, 0
    while start < len(lines) and lines[start].startswith("#"):
        m = re.match(r"#\s*(\w+)\s*=\s*(\S+)", lines[start])
        if m:
            meta[m.group(1).lower()] = m.group(2)
        start += 1
    if start >= len(lines):
        raise InputError("no header row", path)
    head = [s.strip() for s in lines[start].split(",")]
    cols = head[2:]
    if head[:2] != ["frame", "time"] or len(cols) % 3 or not all(c[-2:] in ("_x", "_y", "_z") for c in cols):
        raise InputError("expected a header 'frame,time,<label>_x,<label>_y,<label>_z,...'", path, start + 1)
    labels = _fix_labels([c[:-2] for c in cols[::3]], len(cols) // 3, path, duplicates)
    rows = [ln for ln in lines[start + 1:] if ln.strip()]
    data = np.full((len(rows), len(head)), np.nan)
    for r, line in enumerate(rows):
        parts = line.split(",")
        try:
            data[r, :len(parts)] = [float(s) if s.strip() else np.nan for s in parts[:len(head)]]
        except ValueError:
            raise InputError(f"broken data row: expected {len(head)} numbers", path, start + 2 + r) from None
    if rate is None:
        rate = float(meta["rate"]) if "rate" in meta else (
            1.0 / float(np.median(np.diff(data[:, 1]))) if len(rows) > 1 else None)
    if not rate or not rate > 0:
        raise InputError("frame rate unknown: add '# rate=120' or a time column", path)
    xyz = _gaps_to_nan(data[:, 2:].reshape(len(rows), -1, 3))
    return Markers(xyz, labels, float(rate), units or meta.get("units", "mm"))


READERS = {".c3d": read_c3d, ".trc": read_trc, ".csv": read_csv}
WRITERS = {".c3d": write_c3d, ".trc": write_trc, ".csv": write_csv}


def read_markers(path, duplicates: str = "error") -> Markers:
    """Read a marker file by its extension (.c3d, .trc, .csv)."""
    ext = Path(path).suffix.lower()
    if ext not in READERS:
        raise InputError(f"unknown marker format {ext!r}: expected .c3d, .trc or .csv", path)
    return READERS[ext](path, duplicates=duplicates)


def write_markers(path, markers: Markers) -> None:
    """Write a marker file by its extension (.c3d, .trc, .csv), atomically."""
    ext = Path(path).suffix.lower()
    if ext not in WRITERS:
        raise InputError(f"unknown marker format {ext!r}: expected .c3d, .trc or .csv", path)
    WRITERS[ext](path, markers)
