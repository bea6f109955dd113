"""An artist's blendshape rig: a neutral mesh plus named shapes of one topology (ARKit, FACS, ICT-FaceKit).

Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/rig/model.py``.
"""
from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.formats.obj import Mesh, read_obj, read_obj_vertices

DATA = Path(__file__).parents[1] / "data"
NEUTRAL_NAMES = ("neutral", "generic_neutral_mesh")
ICT_N_VERTICES = 26719
#: Vertices 0..9408 of ICT-FaceKit are the face skin (see ../shared/data/README.md).
ICT_FACE_SKIN = 9409


@dataclass
class Rig:
    """A blendshape rig.

    Attributes
    ----------
    names : list of n_shapes shape names
    neutral : (n_vertices, 3) float64
    deltas : (n_shapes, n_vertices, 3) float64, ``shape - neutral``
    mesh : Mesh, the neutral's topology (faces, UVs, groups)
    files : list of n_shapes Paths
    neutral_file : Path
    value_range : (lo, hi) weights a shape takes (blendshapes: 0..1)
    turned : (3, 3) the rotation :func:`load_rig` gave a rig that was not y-up facing +z, or None
    """

    names: list
    neutral: np.ndarray
    deltas: np.ndarray
    mesh: Mesh | None = None
    files: list = field(default_factory=list)
    neutral_file: Path | None = None
    value_range: tuple = (0.0, 1.0)
    turned: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def n_shapes(self) -> int:
        return len(self.names)

    def evaluate(self, curves: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
        """``neutral + sum_j c_j delta_j`` for (n_frames, n_shapes) curves: (n_frames, n_vertices, 3),
        one matrix product (``vertices`` restricts it to a subset of vertices)."""
        c = np.asarray(curves, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != self.n_shapes:
            raise InputError(f"rig curves: expected (n_frames, {self.n_shapes}), got {c.shape}")
        d = self.deltas if vertices is None else self.deltas[:, vertices]
        n = self.neutral if vertices is None else self.neutral[vertices]
        return n + (c @ d.reshape(self.n_shapes, -1)).reshape(len(c), *n.shape)


def _rig_files(sources: Sequence[str | Path] | str | Path, neutral: str | Path | None):
    if isinstance(sources, (str, Path)):
        sources = [sources]
    files: list[Path] = []
    folder = None
    for s in sources:
        p = Path(s)
        if p.is_dir():
            folder = p
            files += sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() == ".obj")
        else:
            files.append(require_file(p, "rig shape"))
    if neutral is None:
        neutral = next((f for f in files if f.stem.lower() in NEUTRAL_NAMES), None)
    if neutral is None:
        raise InputError("no neutral mesh: give --neutral FILE or put neutral.obj in the rig folder",
                         folder or (files[0] if files else None))
    neutral = require_file(neutral, "rig neutral mesh")
    shapes = [f for f in files if f.resolve() != neutral.resolve() and f.stem.lower() not in NEUTRAL_NAMES]
    if folder is not None and (folder / "vertex_indices.json").is_file():     # ICT-FaceKit layout
        try:
            names = json.loads((folder / "vertex_indices.json").read_text())["expressions"]
        except (json.JSONDecodeError, KeyError, TypeError):
            names = None
        if names:
            keep = set(names)
            shapes = [f for f in shapes if f.stem in keep or f.parent != folder]
    if not shapes:
        raise InputError("no rig shapes (OBJ files besides the neutral) found", folder or neutral)
    from keyshape.retarget.targets.target_set import refuse_name_twins
    refuse_name_twins(shapes, "rig shapes whose names differ only by case")
    return shapes, neutral


def cache_dir() -> Path:
    """Where parsed rigs are cached: ``$KEYSHAPE_CACHE/rigs``, else ``~/.cache/keyshape/rigs``."""
    import os

    root = os.environ.get("KEYSHAPE_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "keyshape") / "rigs"


def _file_hashes(paths: Sequence[Path]) -> list[str]:
    """sha256 of each file's content; a file whose path, device, inode, size, modification time and
    status-change time (ctime) are those recorded in the cache folder's ``hashes.json`` (when its hash
    was last computed) is not read again. The ctime is set by the kernel on every write and cannot be set back (``cp
    -p``, ``rsync -a`` and tar restore the modification time, not the ctime), so a file edited in
    place keeping its size and modification time is hashed again."""
    import os

    from keyshape.base.files import keyshape_store, read_json, sha256_file, write_json

    index_path = cache_dir() / "hashes.json"
    try:
        index = read_json(index_path) if index_path.is_file() else {}
        index = index if isinstance(index, dict) else {}
    except InputError:
        index = {}
    out, changed = [], False
    for p in paths:
        st = os.stat(p)
        key = str(Path(p).resolve())
        rec = index.get(key)
        stamp = [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]
        if isinstance(rec, list) and len(rec) == 6 and rec[:5] == stamp \
                and isinstance(rec[5], str) and len(rec[5]) == 64:
            out.append(rec[5])
            continue
        h = sha256_file(p)
        index[key] = [*stamp, h]
        out.append(h)
        changed = True
    if changed:
        with contextlib.suppress(OSError), keyshape_store():
            write_json(index_path, index, indent=None)
    return out


def rig_digest(files: Sequence[Path], neutral: Path) -> str:
    """sha256 over the content of the rig's files (the neutral, every shape with its name, the .mtl files
    beside the neutral whose colours the mesh carries): the parsed-rig cache's key."""
    import hashlib

    mtl = sorted(neutral.parent.glob("*.mtl"))
    hashes = _file_hashes([neutral, *files, *mtl])
    h = hashlib.sha256(b"keyshape-rig-cache 1\n")
    h.update(f"neutral {hashes[0]}\n".encode())
    for f, fh in zip(files, hashes[1:1 + len(files)]):
        h.update(f"shape {f.stem} {fh}\n".encode())
    for m, mh in zip(mtl, hashes[1 + len(files):]):
        h.update(f"mtl {m.name} {mh}\n".encode())
    return h.hexdigest()


def _parse_rig(files: Sequence[Path], neutral: Path, with_mesh: bool):
    mesh = read_obj(neutral) if with_mesh else None
    base = mesh.vertices if mesh is not None else read_obj_vertices(neutral)
    deltas = np.empty((len(files), len(base), 3))
    for i, f in enumerate(files):
        v = read_obj_vertices(f)
        if len(v) != len(base):
            raise InputError(f"{len(v)} vertices, but the rig's neutral {neutral.name} has {len(base)} "
                             "(rig shapes must share one topology)", f)
        deltas[i] = v - base
    return base, deltas, mesh


def load_rig(sources: Sequence[str | Path] | str | Path, neutral: str | Path | None = None,
             with_mesh: bool = True, cache: bool = True) -> Rig:
    """Load a rig from a folder or a list of OBJ files (see the module docstring).

    Parsed once: the arrays are cached (:mod:`keyshape.base.formats.rigcache`) under :func:`cache_dir`, named by
    :func:`rig_digest` (the files' content); a damaged cache file is parsed again, an unwritable cache folder only
    costs the parsing, ``cache=False`` parses and writes nothing.

    Raises
    ------
    InputError
        No neutral, no shapes, or a shape whose vertex count differs from the neutral's
        (naming that file); duplicate shape names.
    """
    files, neutral = _rig_files(sources, neutral)
    names = [f.stem for f in files]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"rig shape names {dup} appear twice", files[names.index(dup[0])])
    if not cache:
        base, deltas, mesh = _parse_rig(files, neutral, with_mesh)
        return upright(Rig(names, base, deltas, mesh, files, neutral))
    from keyshape.base.formats.rigcache import read_rig_cache, write_rig_cache

    path = cache_dir() / f"{rig_digest(files, neutral)}.npz"
    if path.is_file():
        try:
            cnames, base, deltas, mesh = read_rig_cache(path, with_mesh)
            if cnames == names:
                return upright(Rig(names, base, deltas, mesh if with_mesh else None, files, neutral))
        except InputError:
            pass                                  # damaged: parse again and rewrite it below
    base, deltas, mesh = _parse_rig(files, neutral, True)
    from keyshape.base.files import keyshape_store
    with contextlib.suppress(OSError), keyshape_store():     # a read-only home: the rig is parsed each time
        write_rig_cache(path, names, base, deltas, mesh)
    return upright(Rig(names, base, deltas, mesh if with_mesh else None, files, neutral))


def upright(rig: Rig) -> Rig:
    """The rig turned to the solve's view (y up, the face towards +z) when its shapes say it is not
    (a Z-up rig, or one facing -z): :func:`keyshape.retarget.rig.landmarks.face_axes` from its blinks and
    jawOpen; ``rig.turned`` is the (3, 3) rotation applied (``new = old @ turned.T``), None when none was.
    A rig without those shapes, or whose axes are not clear, is left as it is. Units need no change
    (the solve compares shapes, not sizes)."""
    from keyshape.retarget.rig.landmarks import face_axes
    R = face_axes(rig.neutral, rig.deltas, rig.names)
    rig.turned = None
    if R is None or np.allclose(R, np.eye(3)):
        return rig
    rig.neutral = rig.neutral @ R.T
    rig.deltas = rig.deltas @ R.T
    if rig.mesh is not None:
        rig.mesh = rig.mesh.with_vertices(rig.mesh.vertices @ R.T)
    rig.turned = R
    return rig


def default_landmarks(n_vertices: int, scheme: str) -> Path | None:
    """The shipped landmark correspondence for a rig of this size and scheme, or None."""
    if n_vertices == ICT_N_VERTICES:
        p = DATA / f"ict_landmarks_{scheme}.json"
        return p if p.is_file() else None
    return None


def rig_landmarks(rig: Rig, scheme: str, path: str | Path | None = None, check: bool = True) -> tuple[np.ndarray, Path]:
    """The (n_points, n_vertices) weight matrix taking rig vertices to the scheme's points.

    ``path`` is a rig landmark JSON, or the rig's published iBUG-68 vertex list (a JSON list or one
    index a line: contours48's points are derived from it, :func:`keyshape.retarget.rig.landmarks.contours48_from_ibug68`);
    default: the shipped one for ICT-FaceKit rigs, else the landmarks found on the rig
    (:func:`found_landmarks`; the path returned is then ``Path("automatic")``).
    Raises :class:`InputError` naming the file when it is for another scheme, has another number of points
    than the scheme, or (with ``check``) puts them in an order the rig's geometry refutes
    (:func:`keyshape.retarget.rig.landmarks.landmark_problem`; without, for the page that corrects them).
    """
    from keyshape.base.formats.poses import read_landmark_list, read_rig_landmarks
    from keyshape.base.schemes import load_scheme
    from keyshape.retarget.rig.landmarks import landmark_problem
    sch = load_scheme(scheme)
    if path is None:
        path = default_landmarks(rig.n_vertices, scheme)
        if path is None:
            return found_landmarks(rig, scheme).W, Path("automatic")
    indices = read_landmark_list(path)
    if indices is not None:
        W = _from_published_list(rig, sch, indices, path)
    else:
        s, W = read_rig_landmarks(path, rig.n_vertices)
        if s != scheme:
            raise InputError(f"landmarks are for scheme {s!r}, the keys for {scheme!r}", path)
        if len(W) != sch.n_points:
            hint = (" (iBUG-68's 68 vertex indices? give the list alone, a JSON list or one index a line, and the "
                    f"{scheme} points are derived from it)" if len(W) == 68 else "")
            raise InputError(f"{len(W)} points, scheme {scheme!r} has {sch.n_points}{hint}", path)
    problem = landmark_problem(W @ rig.neutral, sch, rig.neutral.mean(axis=0)) if check else None
    if problem:
        raise InputError(f"these landmarks do not fit the rig: {problem}", path)
    return W, Path(path)


def _from_published_list(rig: Rig, sch, indices: np.ndarray, path) -> np.ndarray:
    """The scheme's weight rows from a rig's published iBUG-68 vertex list (checked)."""
    from keyshape.retarget.rig.landmarks import contours48_on_rig, one_hot
    if len(indices) != 68:
        raise InputError(f"{len(indices)} vertex indices: a rig's published landmark list must hold iBUG-68's 68 "
                         "(jaw 0-16, brows 17-26, nose 27-35, eyes 36-47, lips 48-67)", path)
    bad = indices[(indices < 0) | (indices >= rig.n_vertices)]
    if len(bad):
        raise InputError(f"vertex {int(bad[0])} outside 0..{rig.n_vertices - 1} (this rig has {rig.n_vertices} "
                         "vertices; indices count from 0)", path)
    W68 = one_hot(indices, rig.n_vertices)
    if sch.name == "ibug68":
        return W68
    if sch.name != "contours48":
        raise InputError(f"an iBUG-68 vertex list gives the contours48 or ibug68 schemes' points, not {sch.name!r}",
                         path)
    return contours48_on_rig(W68, rig.neutral, rig.deltas, rig.names).W


def found_landmarks(rig: Rig, scheme: str):
    """The scheme's points found on a rig with no correspondence
    (:func:`keyshape.retarget.rig.landmarks.find_landmarks`), once per rig object:
    a :class:`~keyshape.retarget.rig.landmarks.Derived` (``W``, ``notes``)."""
    from keyshape.retarget.targets.demo import load_expressions
    from keyshape.retarget.rig.landmarks import find_landmarks
    memo = rig.__dict__.setdefault("_found_landmarks", {})
    if scheme not in memo:
        if scheme not in ("contours48", "ibug68"):
            raise InputError(f"no landmark correspondence for this rig ({rig.n_vertices} vertices) and scheme "
                             f"{scheme!r}: give --landmarks FILE (a keyshape-rig-landmarks JSON)", rig.neutral_file)
        mesh = rig.mesh if rig.mesh is not None else read_obj(rig.neutral_file)
        try:
            memo[scheme] = find_landmarks(rig.neutral, rig.deltas, rig.names, mesh.triangles, load_expressions(),
                                          scheme)
        except ValueError as exc:
            raise InputError(f"no landmark correspondence for this rig ({rig.n_vertices} vertices), and none found "
                             f"automatically: {exc}; give --landmarks FILE (the rig's iBUG-68 vertex list or a "
                             "keyshape-rig-landmarks JSON)", rig.neutral_file) from None
        from keyshape.base.schemes import load_scheme
        from keyshape.retarget.rig.landmarks import landmark_problem
        problem = landmark_problem(memo[scheme].W @ rig.neutral, load_scheme(scheme), rig.neutral.mean(axis=0))
        if problem:
            del memo[scheme]
            raise InputError(f"no landmark correspondence for this rig ({rig.n_vertices} vertices), and the one found "
                             f"automatically is wrong ({problem}); give --landmarks FILE (the rig's iBUG-68 vertex "
                             "list or a keyshape-rig-landmarks JSON)", rig.neutral_file)
    return memo[scheme]


def project(points3d: np.ndarray) -> np.ndarray:
    """Orthographic front view of rig points (x right, y up, z to the viewer) in image axes (y down)."""
    p = np.asarray(points3d)
    return np.stack([p[..., 0], -p[..., 1]], axis=-1)


#: ARKit gaze shapes: driven by the pupils region whatever they move (ICT-FaceKit turns its eyeballs
#: with bones, so its ``eyeLook*`` shapes move only the lids, and a lid fit would mistake a blink for gaze).
GAZE_PREFIX = "eyelook"
#: eye rotation (radians) that a full ``eyeLook*`` shape (weight 1) stands for: ARKit's eye range,
#: about 30 degrees sideways and 25 up or down
GAZE_RANGE = (np.radians(30.0), np.radians(25.0))


#: ARKit's gaze shapes: name key -> (column of the eye angles (n_frames, 4): left yaw, left pitch, right yaw,
#: right pitch; the sign of the angle the shape stands for). ``eyeLookOutLeft`` turns the left eye toward
#: the actor's left (yaw > 0), ``eyeLookInLeft`` toward the nose, the right eye mirrored; ``Down``: pitch > 0.
GAZE_SHAPES = {"eyelookoutleft": (0, 1.0), "eyelookinleft": (0, -1.0), "eyelookupleft": (1, -1.0),
               "eyelookdownleft": (1, 1.0), "eyelookoutright": (2, -1.0), "eyelookinright": (2, 1.0),
               "eyelookupright": (3, -1.0), "eyelookdownright": (3, 1.0)}


def gaze_columns(names: Sequence[str]) -> list[tuple[int, int, float]]:
    """``(shape index, angle column, sign)`` of each ARKit gaze shape among ``names`` (:data:`GAZE_SHAPES`)."""
    from keyshape.retarget.targets.target_set import name_key
    return [(j, *GAZE_SHAPES[name_key(n)]) for j, n in enumerate(names) if name_key(n) in GAZE_SHAPES]


def gaze_curves(angles: np.ndarray, names: Sequence[str]) -> tuple[np.ndarray, list[int]]:
    """The rig's ``eyeLook*`` curves from eye angles, and the indices of the shapes they drive.

    ``angles`` (n_frames, 4): left yaw, left pitch, right yaw, right pitch in radians (yaw > 0: toward
    the actor's left; pitch > 0: down; :func:`keyshape.decompose.gaze.gaze_angles`). ARKit's shapes
    (:data:`GAZE_SHAPES`): ``eyeLookOutLeft`` the left eye toward the actor's left, ``eyeLookInLeft`` toward
    the nose, the right eye mirrored; ``eyeLookUp``/``Down`` by pitch; each ``angle / GAZE_RANGE`` clipped
    to [0, 1]. Names match ARKit's and ICT-FaceKit's (``eyeLook_L``) alike.
    """
    a = np.asarray(angles, np.float64)
    out = np.zeros((len(a), len(names)))
    cols = gaze_columns(names)
    for j, col, sign in cols:
        out[:, j] = np.clip(sign * a[:, col] / GAZE_RANGE[col % 2], 0.0, 1.0)
    return out, [j for j, _, _ in cols]


def gaze_pupil_deltas(landmark_neutral: np.ndarray, landmark_deltas: np.ndarray, names: Sequence[str],
                      scheme) -> np.ndarray:
    """The rig's landmark motion per shape with the pupils turned by its gaze shapes.

    A rig's ``eyeLook*`` shapes move the lids but leave the pupil landmarks still (the eyeball turns with a bone);
    here each gaze shape also moves its eye's pupil by ``r sin(angle)`` of its full angle (:data:`GAZE_RANGE`),
    sideways (``eyeLookIn/Out``) or down (``eyeLookDown``; up for ``eyeLookUp``), ``r`` the eyeball's radius on the
    rig's eye (Eq. 1 of :mod:`keyshape.decompose.gaze`).

    Parameters
    ----------
    landmark_neutral : (n_points, 2) the rig's projected scheme points
    landmark_deltas : (n_shapes, n_points, 2) their motion per shape
    names : the rig's shape names
    scheme : the landmark scheme (its pupils and eye corners; unchanged where it has none)

    Returns
    -------
    (n_shapes, n_points, 2) a copy of ``landmark_deltas``
    """
    from keyshape.decompose.gaze import EYE_RADIUS_CM, EYE_WIDTH_CM, EYES, has_gaze
    out = np.array(landmark_deltas, np.float64)
    if not has_gaze(scheme):
        return out
    for j, col, sign in gaze_columns(names):
        eye, pupil = EYES[col // 2]
        a, b = scheme.corners[eye]
        r = EYE_RADIUS_CM / EYE_WIDTH_CM * float(np.linalg.norm(landmark_neutral[b] - landmark_neutral[a]))
        out[j, scheme.contours[pupil][0], col % 2] += sign * r * np.sin(GAZE_RANGE[col % 2])
    return out


def shape_regions(landmark_deltas: np.ndarray, region_points: dict[str, np.ndarray],
                  min_fraction: float = 0.05, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """Regions of rig shapes from their own support: each shape goes to the region whose points it moves most.

    Parameters
    ----------
    landmark_deltas : (n_shapes, n_points, 2) projected motion of the scheme's points per shape
    region_points : {region: point indices}
    min_fraction : a shape whose motion of its region (RMS over the region's points) is below this
        fraction of the largest any shape gives that region drives no region (``PupilDilate``, ``jawForward``)
    names : the shapes' names; ARKit gaze shapes (``eyeLook*``) go to the ``pupils`` region
        (and to no region when there is none)

    Returns
    -------
    {region: indices of the shapes it drives}
    """
    regions = list(region_points)
    rms = np.stack([np.sqrt((landmark_deltas[:, region_points[r]] ** 2).sum(-1).mean(-1)) for r in regions], 1)
    best = np.argmax(rms, axis=1)
    keep = rms.max(axis=1) >= min_fraction * rms.max(axis=0)[best]
    if names is not None:
        gaze = np.array([n.lower().startswith(GAZE_PREFIX) for n in names])
        if "pupils" in regions:
            best[gaze] = regions.index("pupils")
            keep |= gaze
        else:
            keep &= ~gaze
    return {r: np.flatnonzero(keep & (best == i)) for i, r in enumerate(regions)}


#: Base colours (r, g, b, a) by material-name keyword, for OBJ materials without an .mtl ``Kd``;
#: ICT-FaceKit's shading-only shells (lacrimal fluid, eye blend, eye occlusion) are transparent.
MATERIAL_COLOURS = (("teeth", (0.92, 0.9, 0.84, 1.0)), ("sclera", (0.94, 0.94, 0.92, 1.0)),
                    ("iris", (0.22, 0.3, 0.38, 1.0)), ("gum", (0.72, 0.36, 0.36, 1.0)),
                    ("tongue", (0.72, 0.36, 0.36, 1.0)), ("lash", (0.08, 0.06, 0.05, 1.0)),
                    ("lacrimal", (0.9, 0.9, 0.9, 0.0)), ("occlusion", (0.0, 0.0, 0.0, 0.0)),
                    ("blend", (0.8, 0.7, 0.65, 0.0)))
SKIN = (0.8, 0.66, 0.58, 1.0)


def material_colour(mesh: Mesh, name: str) -> tuple:
    """RGBA base colour of material ``name``: the .mtl ``Kd`` when there is one, else by keyword."""
    if name in mesh.material_colours:
        return (*mesh.material_colours[name], 1.0)
    return next((rgba for key, rgba in MATERIAL_COLOURS if key in name.lower()), SKIN)


def triangle_polygons(mesh: Mesh) -> np.ndarray:
    """Polygon index of every triangle of ``mesh.triangles`` (fan triangulation order)."""
    sizes = np.array([len(p) for p in mesh.polygons])
    ok = np.flatnonzero(sizes >= 3)
    return np.repeat(ok, sizes[ok] - 2)


def material_parts(mesh: Mesh) -> list[tuple[str, np.ndarray, tuple]]:
    """[(material, triangle indices, rgba)] covering every triangle (unassigned ones as ``default``)."""
    tp = triangle_polygons(mesh)
    mat = np.full(len(mesh.polygons), -1)
    names = list(mesh.materials)
    for i, n in enumerate(names):
        mat[mesh.materials[n]] = i
    tm = mat[tp]
    parts = [(n, np.flatnonzero(tm == i), material_colour(mesh, n)) for i, n in enumerate(names)]
    if (tm < 0).any():
        parts.append(("default", np.flatnonzero(tm < 0), SKIN))
    return [p for p in parts if len(p[1])]


def support_regions(shapes: np.ndarray, neutral: np.ndarray, columns: Sequence[str],
                    min_fraction: float = 0.02) -> dict[str, np.ndarray]:
    """Region vertex groups from the targets' own support (no hand-made regions file).

    A vertex belongs to the region whose targets move it most (largest displacement
    over that region's targets), if that displacement is at least ``min_fraction`` of
    the largest displacement of any target; columns are ``REGION_K`` (``mouth_3``).
    Regions come out disjoint; :func:`~keyshape.retarget.targets.blend.region_weights` blends
    them across a band.
    """
    from keyshape.retarget.targets.target_set import column_region
    names = list(dict.fromkeys(column_region(c) for c in columns))
    disp = np.linalg.norm(np.asarray(shapes) - neutral, axis=2)          # (n_keys, n_vertices)
    per = np.stack([disp[[i for i, c in enumerate(columns) if column_region(c) == r]].max(axis=0) for r in names])
    best = np.argmax(per, axis=0)
    moved = per.max(axis=0) >= min_fraction * per.max()
    out = {r: np.flatnonzero(moved & (best == i)) for i, r in enumerate(names)}
    empty = [r for r, g in out.items() if not len(g)]
    if empty:
        raise InputError(f"the targets of region(s) {empty} move no vertex: give --regions REGIONS.json")
    return out


#: Mirrored shape names: ``X_L``/``X_R`` (ICT-FaceKit) and ``XLeft``/``XRight`` (ARKit).
MIRROR = (("_L", "_R"), ("Left", "Right"))
#: Shapes whose mirror image is another shape of the other side: the eyes turn together (a look to
#: the actor's left is the left eye's ``eyeLookOut`` and the right eye's ``eyeLookIn``).
CONJUGATE = (("eyeLookIn", "eyeLookOut"), ("eyeLookOut", "eyeLookIn"))


def mirror_pairs(names: Sequence[str]) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)`` of mirrored shapes: names that differ only by the side (``_L``/``_R``,
    ``Left``/``Right``), the horizontal gaze shapes crossed (``eyeLookIn_L`` with ``eyeLookOut_R``, :data:`CONJUGATE`)."""
    pos = {n: i for i, n in enumerate(names)}
    out = []
    for i, n in enumerate(names):
        for a, b in MIRROR:
            if not n.endswith(a):
                continue
            base = n[: -len(a)]
            for x, y in CONJUGATE:
                if base.startswith(x):
                    base = y + base[len(x):]
                    break
            if base + b in pos:
                out.append((i, pos[base + b]))
    return out
