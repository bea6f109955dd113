"""A rig of any topology (issue 39): iBUG-68 vertex lists, refused landmark files, landmarks found automatically,
rigs as they come (units, axes), the check sheet; against the truth of a remeshed ICT-FaceKit rig
(bench/remesh_rig.py), whose true landmarks are known by construction."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from keyshape.base.errors import InputError
from keyshape.base.formats.poses import read_rig_landmarks, write_rig_landmarks
from keyshape.base.schemes import load_scheme
from keyshape.cli import main
from remesh_rig import remeshed_ict_rig
from keyshape.retarget.rig.model import load_rig, project, rig_landmarks

from conftest import gaussian_bumps

SCHEME = load_scheme("contours48")
#: the curves the issue holds the found landmarks to
CHECKED = ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "browInnerUp_R")
ARKIT = {"eyeBlink_L": "eyeBlinkLeft", "eyeBlink_R": "eyeBlinkRight", "mouthSmile_L": "mouthSmileLeft",
         "mouthSmile_R": "mouthSmileRight", "browInnerUp_L": "browInnerUp", "browInnerUp_R": "browInnerUp"}


def _once(fn, memo: dict):
    """``fn`` run once per distinct input (the pickled arguments: equal bytes, equal inputs), a copy of its first
    result given back after that: for pure functions only."""
    import copy
    import hashlib
    import pickle

    def wrapper(*args, **kwargs):
        key = hashlib.sha256(pickle.dumps((args, kwargs))).hexdigest()
        if key not in memo:
            memo[key] = fn(*args, **kwargs)
        return copy.deepcopy(memo[key])
    return wrapper


@pytest.fixture(scope="module", autouse=True)
def searched_once():
    """The landmark search and the remeshing are pure functions of their inputs: in this module each runs once per
    input. The commands given a rig that a test here has already searched (solve, rig-check) take the search's
    result without searching it again; the rigs that share a seed share its remeshing."""
    import remesh_rig as remesh_mod
    import keyshape.retarget.rig.landmarks as landmarks_mod
    memo: dict = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(landmarks_mod, "find_landmarks", _once(landmarks_mod.find_landmarks, memo))
        mp.setattr(remesh_mod, "remesh", _once(remesh_mod.remesh, memo))
        yield memo


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    """The remeshed rig (cm, Y-up), the same rig in metres and Z-up, another face (reshaped, restyled), a face
    reshaped more (1 cm: the mouth corners' motion changes within a fraction of a millimetre there), the
    0.6 cm face cut to its front with ARKit's shape names (a face mask, as ARKit's mesh: ``eyeBlinkLeft``, one
    ``browInnerUp``) and that mask as ARKit's mesh comes (metres, Z-up)."""
    d = tmp_path_factory.mktemp("rigs")
    return {"plain": remeshed_ict_rig(d / "plain", seed=3),
            "m_zup": remeshed_ict_rig(d / "m_zup", seed=3, units="m", up="z"),
            "other_face": remeshed_ict_rig(d / "other_face", seed=8, reshape=0.6),
            "heavy_face": remeshed_ict_rig(d / "heavy_face", seed=5, reshape=1.0),
            "mask": remeshed_ict_rig(d / "mask", seed=8, reshape=0.6, mask=True, arkit=True),
            "arkit": remeshed_ict_rig(d / "arkit", seed=8, reshape=0.6, mask=True, arkit=True, units="m", up="z")}


@pytest.fixture(scope="module")
def loaded(rigs):
    """The rigs loaded (parsed once into the test run's rig cache, which the commands then read)."""
    return {k: load_rig(v["rig"]) for k, v in rigs.items()}


# ---------------------------------------------------------------------------------------- iBUG-68 lists

def test_an_ibug68_list_gives_the_shipped_ict_points(shared_data, tmp_path):
    """ICT-FaceKit's 68 landmark vertices, as a JSON list, one index a line and its own vertex_indices.json:
    contours48's points derived from them are the shipped file's (pupils on the eyeballs included)."""
    from keyshape.retarget.rig.model import DATA
    rig = load_rig(shared_data / "ict-facekit", with_mesh=False)
    ibug = json.loads((shared_data / "ict-facekit" / "vertex_indices.json").read_text())["idx_to_landmark_verts"]
    (tmp_path / "list.json").write_text(json.dumps(ibug))
    (tmp_path / "list.txt").write_text("# iBUG-68, zero-based\n" + "\n".join(map(str, ibug)) + "\n")
    _, shipped = read_rig_landmarks(DATA / "ict_landmarks_contours48.json")
    _, shipped68 = read_rig_landmarks(DATA / "ict_landmarks_ibug68.json")
    for f in (tmp_path / "list.json", tmp_path / "list.txt", shared_data / "ict-facekit" / "vertex_indices.json"):
        W, path = rig_landmarks(rig, "contours48", f)
        assert path == f and np.abs(W - shipped).max() < 1e-6
        assert np.array_equal(rig_landmarks(rig, "ibug68", f)[0], shipped68)


def test_an_ibug68_list_on_a_face_mask_puts_the_pupils_between_the_corners(rigs, loaded, tmp_path, capsys,
                                                                          monkeypatch):
    """On a rig without eyeballs the derived points are the true ones, the pupils midway between each
    eye's corners, and the command says in one line where the gaze then goes."""
    rig, r = loaded["plain"], rigs["plain"]
    W, _ = rig_landmarks(rig, "contours48", r["ibug68"])
    _, truth = read_rig_landmarks(r["landmarks"])
    assert np.abs(W - truth).max() < 1e-6
    assert np.allclose(W[26], 0.5 * (W[10] + W[14])) and np.allclose(W[27], 0.5 * (W[18] + W[22]))
    monkeypatch.setattr("keyshape.retarget.rig.landmarks_cli.SHEET_PANEL", 96)
    assert main(["rig-check", str(r["rig"]), "--landmarks", str(r["ibug68"]), "-o", str(tmp_path / "s.png")]) == 0
    out = capsys.readouterr().out
    assert "no eyeballs" in out and "Live Link's eye angles" in out


def _bad_files(rig, r, folder: Path) -> dict[str, tuple[Path, str]]:
    """Landmark files a user may give by mistake, each with what its one-line refusal must say."""
    _, truth = read_rig_landmarks(r["landmarks"])
    entries = json.loads(Path(r["landmarks"]).read_text())["points"]
    ibug = [int(x) for x in Path(r["ibug68"]).read_text().split()]
    out = {}

    def write(name, points, scheme="contours48"):
        write_rig_landmarks(folder / name, scheme, rig.n_vertices, points)
        return folder / name
    out["44 points"] = (write("short.json", entries[:44]), "44 points, scheme 'contours48' has 48")
    out["iBUG-68 as contours48"] = (write("ibug_as_48.json", ibug), "iBUG-68's 68 vertex indices?")
    out["iBUG's first 48"] = (write("first48.json", ibug[:48]), "not one contour")
    swapped = entries[18:26] + entries[10:18]
    out["eyes swapped"] = (write("eyes.json", entries[:10] + swapped + entries[27:28] + entries[26:27] + entries[28:]),
                           "nearer the right eye")
    out["sides swapped"] = (write("sides.json", entries[5:10] + entries[:5] + swapped + entries[27:28] + entries[26:27]
                                  + entries[28:]), "on the subject's left")
    lips = entries[:28] + entries[34:40] + entries[28:34] + entries[40:]
    out["lips upside down"] = (write("lips.json", lips), "upper points are below its lower ones")
    out["other scheme"] = (write("scheme.json", ibug, "ibug68"), "landmarks are for scheme 'ibug68'")
    (folder / "67.txt").write_text("\n".join(map(str, ibug[:67])))
    out["67 indices"] = (folder / "67.txt", "67 vertex indices")
    (folder / "range.txt").write_text("\n".join(map(str, [rig.n_vertices + 5] + ibug[1:])))
    out["out of range"] = (folder / "range.txt", f"vertex {rig.n_vertices + 5} outside")
    (folder / "words.txt").write_text("12\nthirteen\n")
    out["not an index"] = (folder / "words.txt", "line 2: 'thirteen' is not a vertex index")
    return out


def test_wrong_landmark_files_are_refused_in_one_line(rigs, loaded, tmp_path, capsys):
    """Wrong count, wrong order (iBUG's points as a contours48 file, swapped eyes, lips upside down), another
    scheme, a bad list: each refused naming the file and what is wrong; ``keyshape solve`` exits 2 with one
    line and no traceback, writing nothing."""
    rig, r = loaded["plain"], rigs["plain"]
    take = _take(tmp_path, rig, read_rig_landmarks(r["landmarks"])[1])
    for what, (path, says) in _bad_files(rig, r, tmp_path).items():
        with pytest.raises(InputError) as e:
            rig_landmarks(rig, "contours48", path)
        assert says in str(e.value) and path.name in str(e.value), (what, str(e.value))
        assert main(["solve", *take, "--rig", str(r["rig"]), "--landmarks", str(path),
                     "-o", str(tmp_path / "bad.csv")]) == 2, what
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and says in err, (what, err)
        assert not (tmp_path / "bad.csv").exists()


# ---------------------------------------------------------------------------------------- the remeshed test rig

def test_the_remeshed_rig_is_another_topology_carrying_the_shapes(rigs, loaded):
    """Fewer vertices in another order, a manifold, and the true landmarks move as ICT-FaceKit's do;
    the metres Z-up variant is the same rig turned upright by loading (rig.turned) and scaled."""
    from keyshape.retarget.targets.demo import load_expressions
    from keyshape.retarget.rig.landmarks import contours48_from_ibug68, one_hot
    ex = load_expressions()
    rig = loaded["plain"]
    assert rig.n_vertices < 0.45 * len(ex.neutral) and set(rig.names) == set(ex.names)
    assert not np.allclose(rig.neutral[:100], ex.neutral[:100])          # the vertex order is not ICT's
    tri = np.sort(rig.mesh.triangles, axis=1)
    e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [0, 2]]]), axis=1)
    assert np.unique(e, axis=0, return_counts=True)[1].max() <= 2
    _, truth = read_rig_landmarks(rigs["plain"]["landmarks"])
    W_ict = contours48_from_ibug68(one_hot(ex.landmarks, len(ex.neutral)), ex.neutral).W
    order = [rig.names.index(n) for n in ex.names]
    assert np.abs(truth @ rig.neutral - W_ict @ ex.neutral).max() < 1e-3
    assert np.abs(np.einsum("pv,svc->spc", truth, rig.deltas[order]) -
                  np.einsum("pv,svc->spc", W_ict, ex.deltas)).max() < 1e-3
    mz = loaded["m_zup"]
    assert rig.turned is None and mz.turned is not None
    assert np.abs(mz.neutral * 100 - rig.neutral).max() < 1e-3


# ---------------------------------------------------------------------------------------- found automatically

@pytest.mark.parametrize("kind", ["plain", "m_zup", "other_face", "heavy_face", "mask", "arkit"])
def test_found_landmarks_lie_within_2mm_of_the_truth(rigs, loaded, kind):
    """Every scheme point, inner lips included, within 0.2 cm (ICT's scale) of the true one, in the neutral
    and under every shape (a point on the wrong lip would be 0.3-1 cm off with the jaw open)."""
    from keyshape.retarget.rig.model import found_landmarks
    rig, r = loaded[kind], rigs[kind]
    _, truth = read_rig_landmarks(r["landmarks"])
    found = found_landmarks(rig, "contours48").W
    posed = np.concatenate([rig.neutral[None], rig.neutral + rig.deltas])
    err = np.linalg.norm(np.einsum("pv,svc->spc", found - truth, posed), axis=-1) / r["scale"]
    assert err.max() < 0.2, (kind, err.max(), np.unravel_index(err.argmax(), err.shape))


def _performance(names, n=240, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    C = np.zeros((n, len(names)))

    def bumps(k, width):
        return gaussian_bumps(rng, t, k, width, start=20)
    at = lambda n: names.index(n) if n in names else names.index(ARKIT[n])  # noqa: E731
    C[:, at("jawOpen")] = bumps(5, 10)
    C[:, at("mouthSmile_L")] = C[:, at("mouthSmile_R")] = bumps(4, 12)
    blink = bumps(6, 2)
    blink[int(np.argmax(blink))] = 1.0
    C[:, at("eyeBlink_L")] = C[:, at("eyeBlink_R")] = blink
    C[:, at("browInnerUp_L")] = C[:, at("browInnerUp_R")] = bumps(3, 15)
    C[:20] = 0                                                    # the rest frames
    return C


def _take(folder: Path, rig, W: np.ndarray) -> list[str]:
    """Tracks and keys of an actor who is the rig seen through its true landmarks: [tracks, --keys, keys]."""
    from keyshape.base.formats.keys import RegionKeys, write_keys
    from keyshape.base.formats.tracks import Tracks, write_tracks
    from keyshape.decompose.regions import region_points
    C = _performance(rig.names)
    ln = project(W @ rig.neutral)
    pts = ln[None] + np.einsum("ts,spd->tpd", C, project(np.einsum("pv,svc->spc", W, rig.deltas)))
    s = 100.0 / np.linalg.norm(ln[10] - ln[22])
    img = s * pts + 300.0
    n = len(C)
    pose = np.broadcast_to(np.eye(2, 3), (n, 2, 3))
    write_tracks(folder / "t.csv", Tracks(np.arange(n), np.arange(n) / 30, np.ones(n), np.ones(n, bool), img, pose))
    rest = img[0]
    k = int(np.argmax(C[:, rig.names.index("jawOpen")]))
    regions = [RegionKeys(g, "greedy", region_points(SCHEME, g), np.array([k]), img[k:k + 1, region_points(SCHEME, g)],
                          rest[region_points(SCHEME, g)], None, rest[region_points(SCHEME, g)], 0)
               for g in ("mouth", "eyes")]
    write_keys(folder / "keys.json", "contours48", 48, regions, head_pose={"method": "tracker"})
    return [str(folder / "t.csv"), "--keys", str(folder / "keys.json")]


def _curves(path):
    from keyshape.base.formats.weights import read_weights
    _, cols, values, _ = read_weights(path)
    return {c: values[:, j] for j, c in enumerate(cols)}


@pytest.mark.parametrize("kind", ["plain", "heavy_face", "mask"])
def test_solve_without_landmarks_follows_the_true_landmarks_curves(rigs, loaded, tmp_path, capsys, kind):
    """``keyshape solve`` with no --landmarks on the remeshed rig: one line says the landmarks were found and
    where they were written; the curves follow those of the true landmarks at r >= 0.95; the found file,
    given back with --landmarks, gives the same curves; the rig's iBUG-68 list gives the true file's curves."""
    rig, r = loaded[kind], rigs[kind]
    take = _take(tmp_path, rig, read_rig_landmarks(r["landmarks"])[1])
    solve = ["solve", *take, "--rig", str(r["rig"])]
    assert main([*solve, "--landmarks", str(r["landmarks"]), "-o", str(tmp_path / "true.csv")]) == 0
    capsys.readouterr()
    assert main([*solve, "-o", str(tmp_path / "auto.csv")]) == 0
    out = capsys.readouterr().out
    found = tmp_path / "auto.landmarks.json"
    assert f"no landmark correspondence for this rig ({rig.n_vertices} vertices): found one" in out and str(found) in out
    assert found.is_file()
    true, auto = _curves(tmp_path / "true.csv"), _curves(tmp_path / "auto.csv")
    checked = [n if n in rig.names else ARKIT[n] for n in CHECKED]
    for n in checked:
        assert np.corrcoef(true[n], auto[n])[0, 1] >= 0.95, (n, np.corrcoef(true[n], auto[n])[0, 1])
    assert main([*solve, "--landmarks", str(found), "-o", str(tmp_path / "again.csv")]) == 0
    again = _curves(tmp_path / "again.csv")
    assert all(np.allclose(again[n], auto[n], atol=1e-4) for n in checked)
    assert main([*solve, "--landmarks", str(r["ibug68"]), "-o", str(tmp_path / "ibug.csv")]) == 0
    ibug = _curves(tmp_path / "ibug.csv")
    assert all(np.allclose(ibug[n], true[n], atol=1e-4) for n in true)


def test_a_rig_in_metres_and_z_up_gives_the_curves_of_the_same_rig_in_cm_and_y_up(rigs, loaded, tmp_path):
    take = _take(tmp_path, loaded["plain"], read_rig_landmarks(rigs["plain"]["landmarks"])[1])
    for k in ("plain", "m_zup"):
        assert main(["solve", *take, "--rig", str(rigs[k]["rig"]), "--landmarks", str(rigs[k]["landmarks"]),
                     "-o", str(tmp_path / f"{k}.csv")]) == 0
    a, b = _curves(tmp_path / "plain.csv"), _curves(tmp_path / "m_zup.csv")
    for n in CHECKED:
        assert np.allclose(a[n], b[n], atol=2e-3), n


def test_face_axes_turn_a_rig_upright_whatever_way_it_faces():
    """The rig's own blinks and jawOpen give the rotation back for each axis-aligned way a rig can face."""
    from keyshape.retarget.targets.demo import load_expressions
    from keyshape.retarget.rig.landmarks import face_axes
    ex = load_expressions()
    assert np.array_equal(face_axes(ex.neutral, ex.deltas, ex.names), np.eye(3))
    z_up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])              # Blender: Z up, the face towards -Y
    back = np.diag([-1.0, 1.0, -1.0])                                   # Y up, facing -Z
    side = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])               # Y up, facing +X
    for M in (z_up, back, side, z_up @ side):
        R = face_axes(ex.neutral @ M.T, ex.deltas @ M.T, ex.names)
        assert np.allclose(R @ M, np.eye(3))
    assert face_axes(ex.neutral, ex.deltas[:, :, :] * 0, ex.names) is None
    names = ["eyeBlinkLeft" if n == "eyeBlink_L" else "eyeBlinkRight" if n == "eyeBlink_R" else n for n in ex.names]
    assert np.array_equal(face_axes(ex.neutral, ex.deltas, names), np.eye(3))    # ARKit's spelling


def test_found_landmarks_on_ict_facekit_itself_are_the_shipped_ones(shared_data):
    """The full ICT-FaceKit rig (26,719 vertices with eyeballs, teeth, tongue and eye shells, which are left
    out as pieces of their own): the landmarks found are the shipped file's within 0.05 cm, the pupils on
    the eyeballs found as the shipped ones are."""
    from keyshape.retarget.targets.demo import load_expressions
    from keyshape.retarget.rig.landmarks import find_landmarks
    rig = load_rig(shared_data / "ict-facekit")
    W, _ = rig_landmarks(rig, "contours48")
    found = find_landmarks(rig.neutral, rig.deltas, rig.names, rig.mesh.triangles, load_expressions())
    assert not found.notes
    posed = np.concatenate([rig.neutral[None], rig.neutral + rig.deltas])
    assert np.linalg.norm(np.einsum("pv,svc->spc", found.W - W, posed), axis=-1).max() < 0.05
    assert np.array_equal(found.W[26:28], W[26:28])


def test_rig_check_draws_the_found_landmarks_and_writes_them_beside_the_sheet(rigs, loaded, tmp_path, capsys,
                                                                              monkeypatch):
    import cv2
    r = rigs["m_zup"]
    monkeypatch.setattr("keyshape.retarget.rig.landmarks_cli.SHEET_PANEL", 160)
    assert main(["rig-check", str(r["rig"]), "-o", str(tmp_path / "sheet.png")]) == 0
    img = cv2.imread(str(tmp_path / "sheet.png"))
    assert img.shape[1] > 4 * 160                                      # neutral, blink, jaw open, smile
    assert (tmp_path / "sheet.landmarks.json").is_file()
    assert "found one" in capsys.readouterr().out
    rig = loaded["m_zup"]
    W, _ = rig_landmarks(rig, "contours48", tmp_path / "sheet.landmarks.json")
    _, truth = read_rig_landmarks(r["landmarks"])
    assert (np.linalg.norm((W - truth) @ rig.neutral, axis=1) / r["scale"]).max() < 0.2
