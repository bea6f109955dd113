"""Marker files: C3D (ezc3d), TRC (OpenSim layout) and CSV; one result type, :class:`Markers`.

Design notes and figures: docs/mocap.md, "Notes on the code", ``keyshape/base/formats/markers.py``.
"""
from __future__ import annotations

import hashlib
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path, atomic_write, read_json, write_json
from keyshape.base.formats.tracks import rate_from_times


@dataclass
class Markers:
    """A marker take.

    Attributes
    ----------
    positions : (n_frames, n_markers, 3) float64, NaN in gaps
    labels : list of str, one per marker, unique
    rate : float, frames per second
    units : str, e.g. ``"mm"``
    warnings : list of str, the reader's warnings (commands print them)
    """

    positions: np.ndarray
    labels: list
    rate: float
    units: str = "mm"
    #: what the reader found suspicious but kept (e.g. fewer frames than the header announces)
    warnings: list = field(default_factory=list, compare=False)

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


#: half-size of the largest plausible capture volume, metres (a facial-mocap stage is a few metres)
MAX_METRES = 20.0


def coincident_pairs(points: np.ndarray, tol: float) -> list[tuple[int, int]]:
    """Index pairs of ``points`` (n, 3) closer than ``tol`` (NaN rows ignored)."""
    from scipy.spatial import cKDTree

    ok = np.isfinite(points).all(axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        return []
    pairs = cKDTree(points[idx]).query_pairs(tol)
    return sorted((int(idx[a]), int(idx[b])) for a, b in pairs)


def check_take(m: "Markers", path, n_expected: int | None = None) -> "Markers":
    """Sense checks of a marker take read from ``path``; return it or raise :class:`InputError`.

    Refuses: infinite values, a rate outside (0, 100 kHz], unknown units, a
    position beyond :data:`MAX_METRES` from the origin (corrupt bytes, wrong
    units), a take whose every marker is missing, and a marker set collapsed
    onto one point (more than 2 and more than 10% of the markers coinciding in
    every frame). Warns (``m.warnings``, printed by the commands) of a frame
    count other than the header's ``n_expected`` (a truncated file: the frames
    present are kept) and of a pair of markers coinciding in every frame.
    """
    pos = m.positions
    if m.n_frames == 0:
        raise InputError("no frames", path)
    if n_expected is not None and n_expected != m.n_frames:
        m.warnings.append(f"{path}: the header announces {n_expected} frames but the file holds {m.n_frames} "
                          f"(truncated or damaged file?); using the {m.n_frames} frames present")
    if not (np.isfinite(m.rate) and 0 < m.rate <= 1e5):
        raise InputError(f"frame rate {m.rate}: expected a positive rate up to 100 kHz", path)
    scale = unit_scale(m.units, "m")
    if np.isinf(pos).any():
        raise InputError("infinite coordinates", path)
    far = np.abs(np.nan_to_num(pos)) * scale > MAX_METRES
    if far.any():
        f, k, _ = np.argwhere(far)[0]
        raise InputError(f"marker {m.labels[k]!r} at frame {f} is {np.abs(pos[f, k]).max() * scale:.3g} m from "
                         f"the origin, beyond any capture volume ({MAX_METRES:g} m): damaged file or wrong units "
                         f"({m.units})", path)
    empty = ~np.isfinite(pos).all(axis=2).any(axis=0)
    if empty.all():
        raise InputError("every marker is missing in every frame", path)
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)       # markers missing in every frame: NaN
        med = np.nanmedian(pos, axis=0) if m.n_frames > 1 else pos[0]
    pairs = coincident_pairs(med * scale, 1e-6)
    if pairs:
        same = [(a, b) for a, b in pairs
                if np.nanmax(np.linalg.norm(pos[:, a] - pos[:, b], axis=-1) * scale, initial=0.0) < 1e-6]
        if same:
            names = sorted({m.labels[i] for ab in same for i in ab})
            text = (f"{len(names)} markers coincide in every frame ({', '.join(names[:6])}"
                    f"{', ...' if len(names) > 6 else ''})")
            if len(names) > max(2, 0.1 * m.n_markers):
                raise InputError(text + ": a collapsed marker set (damaged file?)", path)
            m.warnings.append(f"{path}: {text}: duplicated markers, they drive the same point")
    return m


def _gaps_to_nan(p: np.ndarray) -> np.ndarray:
    p = p.copy()
    p[np.all(p == 0.0, axis=-1)] = np.nan
    return p


# ---------------------------------------------------------------------------------------- C3D
def _c3d_contents(path: str) -> dict:
    """What keyshape needs of a C3D file, read with ezc3d (plain arrays and strings)."""
    import ezc3d

    c = ezc3d.c3d(path)
    params = c["parameters"]["POINT"]
    labels = list(params.get("LABELS", {}).get("value", []))
    k = 2
    while f"LABELS{k}" in params:
        labels += list(params[f"LABELS{k}"]["value"])
        k += 1
    meta = c["data"].get("meta_points", {})
    hp = c["header"]["points"]
    return {"points": np.asarray(c["data"]["points"], dtype=np.float64), "labels": [str(s) for s in labels],
            "residuals": np.asarray(meta["residuals"]) if "residuals" in meta else None,
            "rate": np.ravel(params.get("RATE", {}).get("value", [hp["frame_rate"]])).astype(np.float64),
            "units": [str(u) for u in params.get("UNITS", {}).get("value", ["mm"])],
            "first": int(hp["first_frame"]), "last": int(hp["last_frame"])}


def _c3d_header_frames(path: Path) -> int | None:
    """The frame count the C3D file's own header announces (last - first + 1, read from the raw
    bytes: ezc3d adjusts its parsed header to the frames it found, so a file cut short would pass);
    None when the header does not say (16-bit overflow, an unreadable header)."""
    import struct

    try:
        with open(path, "rb") as f:
            head = f.read(512)
            if len(head) < 10 or head[1] != 0x50:
                return None
            f.seek((head[0] - 1) * 512 + 3) if head[0] >= 1 else None
            proc = f.read(1)
    except OSError:
        return None
    order = ">" if proc and proc[0] == 86 else "<"        # 84 Intel, 85 DEC: little-endian; 86 MIPS: big
    first, last = struct.unpack(order + "HH", head[6:10])
    if first < 1 or last < first or last >= 0xFFFF:
        return None
    return last - first + 1


def _limit_memory(extra: int) -> None:  # pragma: no cover (runs in the child process)
    """Cap the address space at its current size plus ``extra`` bytes (a damaged header can make a
    C library try to allocate terabytes)."""
    try:
        import resource

        with open("/proc/self/statm") as f:
            vm = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        want = vm + extra
        if hard == resource.RLIM_INFINITY or want < hard:
            resource.setrlimit(resource.RLIMIT_AS, (want, hard))
    except (OSError, ValueError, ImportError):
        pass


def _child_read(conn, fn, arg, extra) -> None:  # pragma: no cover (runs in the child process)
    try:
        _limit_memory(extra)
        conn.send(("ok", fn(arg)))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent as text
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def _isolated(fn, arg, memory: int = 1 << 30, timeout: float = 300.0):
    """``fn(arg)`` in a forked child process, so that a crash of a C library on a damaged file
    (ezc3d segfaults on some corrupt C3D files) becomes an error instead of killing keyshape.
    The child may allocate ``memory`` bytes more than it starts with and run ``timeout`` seconds.
    Returns ``("ok", result)``, ``("error", text)`` or ``("crash", exit code)``."""
    import multiprocessing as mp

    if "fork" not in mp.get_all_start_methods():       # Windows: no isolation
        try:
            return "ok", fn(arg)
        except Exception as exc:  # noqa: BLE001
            return "error", f"{type(exc).__name__}: {exc}"
    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child_read, args=(send, fn, arg, memory), daemon=True)
    proc.start()
    send.close()
    try:
        try:
            out = recv.recv() if recv.poll(timeout) else ("error", f"no answer in {timeout:.0f} s: damaged file?")
        except EOFError:
            out = None
        proc.join(5.0)
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join()
        recv.close()
    return out if out is not None else ("crash", proc.exitcode)


#: seconds ezc3d may take on a C3D file (plus 1 s per 5 MB) before the file is called damaged
#: (some damaged headers send it into an endless loop)
C3D_SECONDS = 30.0


def read_c3d(path, duplicates: str = "error") -> Markers:
    """Read the 3D points of a C3D file (analogs are ignored).

    ezc3d parses the file in a child process: a damaged file that crashes it is
    reported as an :class:`InputError` like any other unreadable file.
    """
    path = require_file(path, "C3D file")
    size = path.stat().st_size
    status, c = _isolated(_c3d_contents, str(path), memory=(1 << 30) + 64 * size,
                          timeout=C3D_SECONDS + size / 5e6)
    if status == "crash":
        raise InputError(f"not a readable C3D file (damaged: the C3D reader crashed, exit {c})", path)
    if status == "error":
        raise InputError(f"not a readable C3D file ({c})", path)
    pts = c["points"]  # (4, n_markers, n_frames)
    if pts.ndim != 3 or pts.shape[0] < 3:
        raise InputError(f"not a readable C3D file (points of shape {pts.shape})", path)
    n = pts.shape[1]
    if n == 0:
        raise InputError("the C3D file holds no 3D points", path)
    labels = _fix_labels(c["labels"], n, path, duplicates)
    xyz = pts[:3].transpose(2, 1, 0)
    res = c["residuals"]
    if res is not None and res.ndim == 3 and res.shape[1:] == pts.shape[1:]:
        xyz[res[0].T < 0] = np.nan
    xyz = _gaps_to_nan(xyz)
    rate = float(c["rate"][0]) if len(c["rate"]) else float("nan")
    units = (c["units"][0] if len(c["units"]) else "mm").strip() or "mm"
    if not rate > 0:
        raise InputError(f"POINT:RATE is {rate}: expected a positive frame rate", path)
    announced = _c3d_header_frames(path)
    return check_take(Markers(xyz, labels, rate, units), path,
                      announced if announced is not None else c["last"] - c["first"] + 1)


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
        n_frames = int(head["NumFrames"]) if head.get("NumFrames") else None
    except (KeyError, ValueError):
        raise InputError("header needs DataRate and NumMarkers values", path, 3) from None
    if not 0 < n_markers <= 100000:
        raise InputError(f"NumMarkers {n_markers}: expected 1 to 100000", path, 3)
    units = head.get("Units", "mm") or "mm"
    cells = [s.strip() for s in lines[3].split(sep)[2:]]
    names = [cells[3 * k] if 3 * k < len(cells) else "" for k in range(n_markers)]   # X column of each
    packed = [s for s in cells if s]
    if "" in names and len(packed) == n_markers:
        names = packed                          # labels not on the X/Y/Z grid but one per marker
    labels = _fix_labels(names, n_markers, path, duplicates)
    row_ln = [ln + 1 for ln in range(5, len(lines)) if lines[ln].split(sep)[0].strip()]
    rows = [lines[ln - 1] for ln in row_ln]
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
    fr = data[:, 0]
    if not np.isfinite(fr).all() or (np.diff(fr) != 1).any():
        bad = int(np.flatnonzero(~np.isfinite(fr[1:]) | (np.diff(fr) != 1))[0]) + 1 if len(fr) > 1 else 0
        raise InputError(f"Frame# {fr[bad]:g} after {fr[bad - 1]:g}: frame numbers must be unique, sorted and "
                         "contiguous", path, row_ln[bad])
    xyz = _gaps_to_nan(data[:, 2:].reshape(len(rows), n_markers, 3))
    return check_take(Markers(xyz, labels, rate, units), path, n_frames)


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
#: key that marks a JSON file as a marker CSV's sidecar written by keyshape
CSV_META_KEY = "keyshape_markers"


def _csv_meta_path(path: Path) -> Path:
    return path.with_name(path.stem + ".meta.json")


def write_csv(path, markers: Markers) -> None:
    """Write ``frame,time,<label>_x,...`` and the sidecar ``NAME.meta.json`` (rate, units), atomically."""
    nf = markers.n_frames
    head = "frame,time," + ",".join(f"{s}_{a}" for s in markers.labels for a in "xyz")
    cells = _fmt(markers.positions.reshape(nf, -1))
    body = [",".join([str(i), f"{t:.6f}", *row]) for i, (t, row) in enumerate(zip(markers.times, cells))]
    text = f"{head}\n" + "\n".join(body) + "\n"
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="\n", encoding="utf-8") as f:     # the bytes on disk are the text hashed
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        write_json(_csv_meta_path(path), {CSV_META_KEY: 1, "csv_sha256": hashlib.sha256(text.encode()).hexdigest(),
                                          "rate": float(markers.rate), "units": markers.units})


def _read_csv_meta(path: Path) -> dict:
    """The sidecar's ``rate``/``units`` for the marker CSV ``path`` ({} if none, not keyshape's, or stale)."""
    side = _csv_meta_path(path)
    if not side.is_file():
        return {}
    meta = read_json(side, "marker CSV sidecar")
    if not isinstance(meta, dict) or CSV_META_KEY not in meta:
        return {}
    if meta.get("csv_sha256") != hashlib.sha256(path.read_bytes()).hexdigest():
        warnings.warn(f"{side}: written for another version of {path.name} (the CSV changed since); "
                      "its rate and units are ignored", stacklevel=3)
        return {}
    return {k: str(meta[k]) for k in ("rate", "units") if k in meta}


def read_csv(path, rate: float | None = None, units: str | None = None, duplicates: str = "error") -> Markers:
    """Read the CSV layout written by :func:`write_csv` (``rate`` and ``units`` from the sidecar or an
    older file's comments, else the rate from the time column and mm)."""
    path = require_file(path, "CSV file")
    lines = path.read_text(errors="replace").splitlines()
    meta, start = {}, 0
    while start < len(lines) and lines[start].startswith("#"):
        m = re.match(r"#\s*(\w+)\s*=\s*(\S+)", lines[start])
        if m:
            meta[m.group(1).lower()] = m.group(2)
        start += 1
    if not start:
        meta = _read_csv_meta(path)
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
            rate_from_times(len(rows) - 1, float(data[-1, 1] - data[0, 1])) if len(rows) > 1 else None)
    if not rate or not rate > 0:
        raise InputError("frame rate unknown: give the time column (seconds) of at least two frames", path)
    fr = data[:, 0]
    if not np.isfinite(fr).all() or (np.diff(fr) != 1).any():
        raise InputError("frame numbers must be unique, sorted and contiguous", path)
    xyz = _gaps_to_nan(data[:, 2:].reshape(len(rows), -1, 3))
    return check_take(Markers(xyz, labels, float(rate), units or meta.get("units", "mm")), path)


READERS = {".c3d": read_c3d, ".trc": read_trc, ".csv": read_csv}
WRITERS = {".c3d": write_c3d, ".trc": write_trc, ".csv": write_csv}


def _by_extension(path, table: dict):
    ext = Path(path).suffix.lower()
    if ext not in table:
        raise InputError(f"unknown marker format {ext!r}: expected .c3d, .trc or .csv", path)
    return table[ext]


def read_markers(path, duplicates: str = "error") -> Markers:
    """Read a marker file by its extension (.c3d, .trc, .csv)."""
    return _by_extension(path, READERS)(path, duplicates=duplicates)


def write_markers(path, markers: Markers) -> None:
    """Write a marker file by its extension (.c3d, .trc, .csv), atomically."""
    _by_extension(path, WRITERS)(path, markers)


# --------------------------------------------------------------------------- markers on a mesh (JSON)

def read_mesh_markers(path, what: str = "markers") -> dict:
    """Read a mesh-markers JSON -> ``{name: vertex index (int) or [x, y, z]}``.

    Values may also be ``{"position": [x, y, z], "vertex": i}`` as
    :func:`write_mesh_markers` writes them (``keyshape register --out-markers``); the position is used.
    """
    data = read_json(path, what)
    if isinstance(data, list):
        data = {str(i): m for i, m in enumerate(data)}
    if not isinstance(data, dict) or not data:
        raise InputError("expected {\"name\": vertex index or [x, y, z], ...}", path)
    out = {}
    for k, m in data.items():
        if isinstance(m, dict) and "position" in m:
            m = m["position"]
        ok = (isinstance(m, int) and not isinstance(m, bool)) or (
            isinstance(m, list) and len(m) == 3 and all(isinstance(c, (int, float)) for c in m))
        if not ok:
            raise InputError(f"marker {k!r}: expected a vertex index or [x, y, z], got {m!r:.60}", path)
        out[str(k)] = m
    return out


def write_mesh_markers(path, placed: dict) -> None:
    """Write placed markers ``{name: {"position": [x, y, z], "vertex": i}}`` (or plain
    ``{name: vertex or [x, y, z]}``) as a mesh-markers JSON, atomically."""
    write_json(path, placed)
