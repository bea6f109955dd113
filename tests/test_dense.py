"""Dense-mesh tools: face-space RBF, key-point insertion, transfer, registration, formats (issue 7)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from keyshape.cli import main
from keyshape.base.errors import InputError, NotFittedError
from keyshape.base.formats.keypoints import read_keypoints
from keyshape.base.formats.pairs import read_pairs
from keyshape.base.formats.sequence import read_sequence, write_sequence
from keyshape.retarget.dense.keypoints import KeyPointInserter, random_insertion, sequence_errors
from keyshape.retarget.dense.meshcheck import TriangleSurface, check_mesh, closest_on_triangles
from keyshape.retarget.dense.keypoints import face_rbf
from keyshape.retarget.dense.registration import (MeshEnergy, place_markers, register_mesh, resolve_landmarks,
                                         transfer_masks)
from keyshape.retarget.dense.transfer import transfer_sequence


def grid(n=21, size=10.0):
    """An n x n grid sheet in the xy plane, triangulated, (vertices, triangles)."""
    x, y = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def bump_sequence(n_frames=12, n=25):
    """A sheet with a Gaussian bump that rises and falls at (7, 7) plus a gentle global wave."""
    v, t = grid(n)
    s = np.sin(np.linspace(0, np.pi, n_frames))[:, None]
    bump = np.exp(-((v[:, 0] - 7) ** 2 + (v[:, 1] - 7) ** 2) / 2.0)[None]
    frames = np.repeat(v[None], n_frames, 0)
    frames[:, :, 2] = 2.0 * s * bump + 0.3 * s * np.sin(v[:, 0] / 3)[None]
    return frames, t


# --- face-space RBF (eqs. 1-5) -------------------------------------------------------------------
def test_rbf_reproduces_keys_and_identity():
    rng = np.random.default_rng(0)
    k0 = rng.uniform(0, 10, (20, 3))
    kt = k0 + rng.normal(scale=0.5, size=(4, 20, 3))
    rbf = face_rbf(None, 0.0).fit(k0)
    assert np.allclose(rbf.deform(k0, kt), kt, atol=1e-6)           # eq. 1: keys go exactly to K^t
    x = rng.uniform(0, 10, (50, 3))
    assert np.allclose(rbf.deform(x, k0), x)                        # K^t = K^0 is the identity
    batch = rbf.deform(x, kt)
    assert np.allclose(batch[2], rbf.deform(x, kt[2]))              # batched frames = one at a time
    far = x + 1e3
    assert np.allclose(rbf.deform(far, kt[0]), far)                 # far from every key: no motion


def test_rbf_rejects_coincident_keys():
    with pytest.raises(InputError, match="coincide"):
        face_rbf(None, 1e-2).fit(np.zeros((3, 3)))


# --- key-point insertion (section 5) --------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_insertion_beats_initial_and_random(seed):
    frames, _ = bump_sequence()
    rng = np.random.default_rng(seed)
    # initial keys on the border, far from the bump
    n = 25
    border = np.r_[np.arange(0, n, 6), np.arange(n * (n - 1), n * n, 6), np.arange(0, n * n, 6 * n)]
    init = np.unique(border)
    ins = KeyPointInserter(radius=1.5, n_candidates=400, max_new=6, sigma=1.0, rng=rng).fit(frames, init)
    e_init = sequence_errors(ins.deform(frames, init, frames[:, init]), frames)["mean"]
    e_ins = sequence_errors(ins.reconstruct(frames), frames)["mean"]
    n_new = len(ins.key_indices_) - len(init)
    assert n_new > 0 and e_ins < 0.5 * e_init
    ri, rp = random_insertion(frames, init, n_new, 1.5, rng=seed, sigma=1.0)
    e_rand = sequence_errors(ins.deform(frames, ri, rp), frames)["mean"]
    assert e_ins < e_rand
    # history is monotone and stops by the 1 % rule or max_rounds
    errs = [h["mean_error"] for h in ins.history_]
    assert all(b < a for a, b in zip(errs, errs[1:]))


def test_insertion_without_correspondence_runs_and_helps():
    frames, _ = bump_sequence()
    init = np.array([0, 24, 600, 624, 312])
    ins = KeyPointInserter(radius=1.5, n_candidates=400, max_new=6, sigma=1.0, correspondence=False, rng=0).fit(frames, init)
    errs = [h["mean_error"] for h in ins.history_]      # measured 0.145 -> 0.076 (5 -> 9 keys)
    assert errs[-1] < 0.7 * errs[0] and len(ins.key_indices_) > len(init)


def test_inserter_errors():
    frames, _ = bump_sequence()
    with pytest.raises(NotFittedError, match="not fitted"):
        KeyPointInserter().reconstruct(frames)
    with pytest.raises(InputError, match="must lie in"):
        KeyPointInserter().fit(frames, np.array([0, 10_000]))
    with pytest.raises(InputError, match="n_frames"):
        KeyPointInserter().fit(frames[0], np.array([0, 1]))


# --- facial transfer (section 6) ------------------------------------------------------------------
def test_transfer_properties():
    frames, _ = bump_sequence(n_frames=6)
    keys = np.array([0, 24, 600, 624, 312, 100, 500])
    target = frames[0] * 1.1
    still = transfer_sequence(frames, keys, target, keys, gain=0.0, n_samples=200, rng=0)
    assert np.allclose(still, target[None])                          # gain 0: nothing moves
    out = transfer_sequence(frames, keys, target, keys, n_samples=200, rng=0)
    assert np.allclose(out[0], target)                               # neutral goes to the neutral target
    # the bump's rise shows on the target where the source moved (frame 3 is the peak)
    peak = np.argmin(np.linalg.norm(frames[0] - [7, 7, 0], axis=1))
    assert out[3, np.argmin(np.linalg.norm(target - target[peak], axis=1)), 2] > 0.5



def test_transfer_onto_own_neutral_reproduces_the_sequence():
    """Identity transfer: the bump sequence carried onto its own neutral comes back (tangential motion too)."""
    frames, _ = bump_sequence(n_frames=6)
    frames[:, :, 0] += 0.5 * np.sin(np.linspace(0, np.pi, 6))[:, None] * np.exp(
        -((frames[0, :, 0] - 5) ** 2 + (frames[0, :, 1] - 5) ** 2) / 8.0)[None]   # sliding skin
    keys = np.array([0, 24, 600, 624, 312])
    out = transfer_sequence(frames, keys, frames[0], keys, n_samples=300, rng=0)
    err = np.linalg.norm(out[1:] - frames[1:], axis=2).mean()
    motion = np.linalg.norm(frames[1:] - frames[:1], axis=2).mean()
    assert err < 0.1 * motion


def _ict_case(ict, step=3, n_frames=6):
    """A decimated ICT "talk" case: every ``step``-th face-skin vertex, ``n_frames`` frames, 68 landmarks as keys."""
    from dense_synth import dense_sequence
    from keyshape.base.formats.obj import read_obj_vertices
    frames, _ = dense_sequence(ict, "talk", n_frames, rng=0)
    lm68 = np.array(json.loads((ict / "vertex_indices.json").read_text())["idx_to_landmark_verts"])
    keep = np.union1d(np.arange(0, 9409, step), lm68[lm68 < 9409])
    keys = np.searchsorted(keep, lm68[lm68 < 9409])
    ident = read_obj_vertices(ict / "identity000.obj")[keep]
    return frames[:, keep], keys, ident


def _rel(out, truth):
    err = np.linalg.norm(out[1:] - truth[1:], axis=2).mean()
    return err, np.linalg.norm(truth[1:] - truth[:1], axis=2).mean()


def test_ict_transfer_identity_and_onto_identity000(shared_data):
    frames, keys, ident = _ict_case(shared_data / "ict-facekit")
    out = transfer_sequence(frames, keys, frames[0], keys, n_samples=1500, rng=0)
    err, motion = _rel(out, frames)
    assert err < 0.2 * motion                      # own neutral: the sequence comes back
    truth = ident[None] + frames - frames[0]       # same expression deltas on identity000
    out = transfer_sequence(frames, keys, ident, keys, n_samples=1500, rng=0)
    err, still = _rel(out, truth)                  # "no motion" leaves an error of the motion itself
    assert err < 0.25 * still


@pytest.mark.slow
@pytest.mark.parametrize("target", ["self", "identity000", "identity003"])
def test_ict_transfer_full_size(shared_data, target):
    from dense_synth import dense_sequence
    from keyshape.base.formats.obj import read_obj_vertices
    ict = shared_data / "ict-facekit"
    frames, _ = dense_sequence(ict, "talk", 8, rng=0)
    lm68 = np.array(json.loads((ict / "vertex_indices.json").read_text())["idx_to_landmark_verts"])
    tv = frames[0] if target == "self" else read_obj_vertices(ict / f"{target}.obj")
    out = transfer_sequence(frames, lm68, tv, lm68, rng=0)
    skin = slice(0, 9409)
    err, motion = _rel(out[:, skin], (tv[None] + frames - frames[0])[:, skin])
    assert err < 0.25 * motion

# --- mesh checks and closest points ------------------------------------------------------------
def test_closest_on_triangles_against_dense_sampling():
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 200, 3))
    p = rng.normal(size=(200, 3)) * 2
    q = closest_on_triangles(p, a, b, c)
    uv = rng.uniform(size=(4000, 2))
    uv = np.where(uv.sum(1, keepdims=True) > 1, 1 - uv, uv)
    samples = a[:, None] + uv[None, :, :1] * (b - a)[:, None] + uv[None, :, 1:] * (c - a)[:, None]
    best = np.linalg.norm(samples - p[:, None], axis=2).min(1)
    got = np.linalg.norm(q - p, axis=1)
    assert np.all(got <= best + 1e-9) and np.all(best - got < 0.1)


def test_check_mesh_errors():
    v, t = grid(4)
    check_mesh(v, t)
    with pytest.raises(InputError, match="no faces"):
        check_mesh(v, np.zeros((0, 3), int), "target mesh")
    with pytest.raises(InputError, match="degenerate"):
        check_mesh(v, np.r_[t, [[0, 0, 1]]])
    flat = v.copy()
    with pytest.raises(InputError, match="degenerate"):
        check_mesh(flat, np.r_[t, [[0, 1, 2]]])                     # collinear: zero area
    with pytest.raises(InputError, match="non-manifold"):
        check_mesh(np.r_[v, [[0, 0, 5.0], [0, 0, -5.0]]], np.r_[t, [[0, 1, len(v)], [1, 0, len(v) + 1]]])
        # border edge (0, 1) now has three faces


# --- registration (001 section 6) --------------------------------------------------------------
def curved(v, amp=1.0):
    w = v.copy()
    w[:, 2] = amp * np.sin(v[:, 0] / 4) * np.cos(v[:, 1] / 5)
    return w


def test_energy_gradient_matches_finite_differences():
    v, t = grid(8)
    v = curved(v, 0.5)
    rng = np.random.default_rng(0)
    surf = TriangleSurface(curved(v, 1.0), t)
    basis = rng.normal(size=(len(v), 5)) * 0.1
    e = MeshEnergy(v, t, basis, np.arange(len(v)), surf, 1.0, 1.0, 0.5, 1.0, np.array([0, 9]), v[[0, 9]] + 0.1)
    x = rng.normal(size=15) * 0.05
    f0, g = e(x)
    num = np.array([(e(x + h)[0] - e(x - h)[0]) / 2e-6 for h in np.eye(15) * 1e-6])
    assert np.allclose(g, num, rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("solver", ["lbfgs", "simplex"])
def test_registration_fits_a_bent_sheet(solver):
    v, t = grid(15)
    target = curved(v, 1.5)
    lm = [0, 14, 210, 224, 112, 52, 172]
    pairs = [{"reference": i, "target": i} for i in lm]
    res = register_mesh(v, t, target, t, pairs, solver=solver, n_controls=25, max_evals=300 if solver == "lbfgs"
                        else 400)
    err_warp = np.linalg.norm(res.warped - target, axis=1).mean()
    err_fit = np.linalg.norm(res.vertices - target, axis=1).mean()
    assert res.energy < res.energy_start
    if solver == "lbfgs":
        assert err_fit < 0.5 * err_warp


def test_markers_and_masks_follow_the_fit():
    v, t = grid(11)
    target = v * 1.2
    res_vertices = target.copy()  # a perfect fit
    placed = place_markers({"a": 5, "b": [1.0, 1.0, 0.0]}, v, t, res_vertices, target, t)
    assert placed["a"]["vertex"] == 5 and np.allclose(placed["a"]["position"], target[5])
    assert np.allclose(placed["b"]["position"], [1.2, 1.2, 0.0])
    masks = transfer_masks({"m": [0, 1, 2]}, res_vertices, target)
    assert masks["m"].tolist() == [0, 1, 2]


def test_landmark_errors():
    v, t = grid(5)
    with pytest.raises(InputError, match=r"PAIRS\.json.*at least 4"):
        resolve_landmarks([{"reference": 0, "target": 0}] * 3, v, v, "PAIRS.json")
    pairs = [{"reference": i, "target": i} for i in (0, 4, 20, 24)]
    with pytest.raises(InputError, match=r"PAIRS\.json.*target vertex 99 does not exist"):
        resolve_landmarks(pairs[:3] + [{"reference": 12, "target": 99}], v, v, "PAIRS.json")
    with pytest.raises(InputError, match="vertex index or"):
        resolve_landmarks(pairs[:3] + [{"reference": "nose", "target": 1}], v, v, "PAIRS.json")


# --- formats and commands ------------------------------------------------------------------------
def test_sequence_roundtrip_and_errors(tmp_path):
    frames, t = bump_sequence(4, 6)
    write_sequence(tmp_path / "s.npz", frames, t)
    f2, t2 = read_sequence(tmp_path / "s.npz")
    assert np.array_equal(f2, frames) and np.array_equal(t2, t)
    np.savez(tmp_path / "bad.npz", points=frames)
    with pytest.raises(InputError, match=r"bad\.npz.*no 'vertices'"):
        read_sequence(tmp_path / "bad.npz")
    (tmp_path / "p.json").write_text("{not json")
    with pytest.raises(InputError, match=r"p\.json.*not valid JSON"):
        read_pairs(tmp_path / "p.json")


def test_cli_register_and_keypoints(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("keyshape.retarget.dense.cli.CONTROLS", 20)
    monkeypatch.setattr("keyshape.retarget.dense.cli.SAMPLES", 225)
    from keyshape.base.formats.obj import Mesh, read_obj, write_obj
    v, t = grid(11)
    write_obj(tmp_path / "ref.obj", Mesh(v, list(t)))
    write_obj(tmp_path / "tgt.obj", Mesh(curved(v, 0.8), list(t)))
    pairs = [{"reference": i, "target": i} for i in (0, 10, 110, 120, 60)]
    (tmp_path / "pairs.json").write_text(json.dumps(pairs))
    (tmp_path / "m.json").write_text(json.dumps({"tip": 60}))
    rc = main(["register", str(tmp_path / "ref.obj"), str(tmp_path / "tgt.obj"), "--landmarks",
               str(tmp_path / "pairs.json"), "-o", str(tmp_path / "fit.obj"),
               "--markers", str(tmp_path / "m.json"), "--out-markers", str(tmp_path / "tm.json")])
    assert rc == 0 and read_obj(tmp_path / "fit.obj").n_vertices == len(v)
    assert json.loads((tmp_path / "tm.json").read_text())["tip"]["vertex"] == 60
    (tmp_path / "few.json").write_text(json.dumps(pairs[:3]))
    rc = main(["register", str(tmp_path / "ref.obj"), str(tmp_path / "tgt.obj"), "--landmarks",
               str(tmp_path / "few.json"), "-o", str(tmp_path / "x.obj")])
    assert rc == 2 and "few.json" in capsys.readouterr().err
    write_obj(tmp_path / "nofaces.obj", Mesh(v, []))
    rc = main(["register", str(tmp_path / "ref.obj"), str(tmp_path / "nofaces.obj"), "--landmarks",
               str(tmp_path / "pairs.json"), "-o", str(tmp_path / "x.obj")])
    assert rc == 2 and "nofaces.obj" in capsys.readouterr().err
    frames, tri = bump_sequence(8, 15)
    write_sequence(tmp_path / "seq.npz", frames, tri)
    rc = main(["keypoints", str(tmp_path / "seq.npz"), "--initial", "6", "-o", str(tmp_path / "k.json")])
    assert rc == 0 and len(read_keypoints(tmp_path / "k.json")) >= 6
    rc = main(["transfer", str(tmp_path / "seq.npz"), "--target", str(tmp_path / "ref.obj"),
               "-o", str(tmp_path / "o.npz")])
    assert rc == 2 and "ref.obj" in capsys.readouterr().err        # different point counts, no landmarks
    write_obj(tmp_path / "self.obj", Mesh(frames[0], list(tri)))
    rc = main(["transfer", str(tmp_path / "seq.npz"), "--target", str(tmp_path / "self.obj"), "--keypoints",
               str(tmp_path / "k.json"), "-o", str(tmp_path / "o.npz")])
    out, _ = read_sequence(tmp_path / "o.npz")
    assert rc == 0 and out.shape == frames.shape
    assert np.linalg.norm(out - frames, axis=2).mean() < 0.1 * np.linalg.norm(frames - frames[0], axis=2).mean()


# --- ICT-FaceKit accuracy (slow) -------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("target", [
    "identity001",
    pytest.param("realistic", marks=pytest.mark.xfail(strict=True, reason=(
        "issue 7 target not met for a face several cm different: the fit slides along the sides of the head "
        "and under the chin, far from the 12 frontal landmarks (docs/keypoints.md)"))),
])
def test_ict_registration_halves_error_and_places_markers(shared_data, target):
    from dense_synth import LANDMARKS68, realistic_face
    from keyshape.base.formats.obj import read_obj, read_obj_vertices
    ict = shared_data / "ict-facekit"
    ref = read_obj(ict / "generic_neutral_mesh.obj")
    lm68 = np.array(json.loads((ict / "vertex_indices.json").read_text())["idx_to_landmark_verts"])
    ids = [read_obj_vertices(ict / f"identity00{i}.obj") for i in range(4)]
    tv = ids[1] if target == "identity001" else realistic_face(ref.vertices, ids, 0)
    pairs = [{"reference": int(lm68[i]), "target": int(lm68[i])} for i in LANDMARKS68]
    res = register_mesh(ref.vertices, ref.triangles, tv, ref.triangles, pairs)
    skin = slice(0, 9409)
    warp = np.linalg.norm(res.warped[skin] - tv[skin], axis=1).mean()
    fit = np.linalg.norm(res.vertices[skin] - tv[skin], axis=1).mean()
    placed = place_markers({str(i): int(v) for i, v in enumerate(lm68)}, ref.vertices, ref.triangles,
                           res.vertices, tv, ref.triangles)
    err = np.mean([np.linalg.norm(np.array(placed[str(i)]["position"]) - tv[v]) for i, v in enumerate(lm68)])
    assert fit < 0.5 * warp and err < 0.2  # half the error; markers within 2 mm (mesh units are cm)


@pytest.mark.slow
@pytest.mark.parametrize("performance", ["talk", "stretch"])
def test_ict_insertion_beats_random(shared_data, performance):
    from dense_synth import dense_sequence
    ict = shared_data / "ict-facekit"
    lm68 = np.array(json.loads((ict / "vertex_indices.json").read_text())["idx_to_landmark_verts"])
    frames, _ = dense_sequence(ict, performance, 60, rng=0)
    ins = KeyPointInserter(rng=0).fit(frames, lm68)
    skin = np.arange(9409)
    init = sequence_errors(ins.deform(frames, lm68, frames[:, lm68]), frames, skin)
    fin = sequence_errors(ins.reconstruct(frames), frames, skin)
    n_new = len(ins.key_indices_) - len(lm68)
    rnd = sequence_errors(ins.deform(frames, *random_insertion(frames, lm68, n_new, ins.radius_, rng=0)), frames,
                          skin)
    assert fin["mean"] < init["mean"] and fin["mean"] < rnd["mean"] and fin["rmse"] < rnd["rmse"]


@pytest.mark.slow
def test_dense_sequences_are_deterministic(shared_data):
    from dense_synth import dense_sequence
    a, tri = dense_sequence(shared_data / "ict-facekit", "smile", 5, rng=3)
    b, _ = dense_sequence(shared_data / "ict-facekit", "smile", 5, rng=3)
    c, _ = dense_sequence(shared_data / "ict-facekit", "smile", 5, rng=4)
    assert a.shape == (5, 26719, 3) and np.array_equal(a, b) and not np.array_equal(a, c)
    with pytest.raises(InputError, match="unknown performance"):
        dense_sequence(shared_data / "ict-facekit", "sneeze")


def test_register_outputs_feed_the_mocap_command(tmp_path, monkeypatch):
    monkeypatch.setattr("keyshape.retarget.dense.cli.CONTROLS", 20)
    """``register --out-markers/--out-masks`` write what ``keyshape mocap --target-markers/--masks`` reads."""
    from keyshape.retarget.mocap.cli import read_target_markers
    from keyshape.base.formats.masks import read_masks
    from keyshape.retarget.mocap.masks import regions_from_masks
    from keyshape.base.formats.obj import Mesh, write_obj
    v, t = grid(11)
    write_obj(tmp_path / "ref.obj", Mesh(v, list(t)))
    write_obj(tmp_path / "tgt.obj", Mesh(v.copy(), list(t)))       # same face: masks must carry unchanged
    pairs = [{"reference": i, "target": i} for i in (0, 10, 110, 120, 60)]
    (tmp_path / "pairs.json").write_text(json.dumps(pairs))
    (tmp_path / "m.json").write_text(json.dumps({"tip": 60, "corner": 0, "edge": 5, "far": 120}))
    lower = list(range(0, 55))
    masks = {"regions": [{"name": "lower", "vertices": lower, "exclude_markers": ["far"]}], "note": "kept"}
    (tmp_path / "masks.json").write_text(json.dumps(masks))
    rc = main(["register", str(tmp_path / "ref.obj"), str(tmp_path / "tgt.obj"), "--landmarks",
               str(tmp_path / "pairs.json"), "-o", str(tmp_path / "fit.obj"),
               "--markers", str(tmp_path / "m.json"), "--out-markers", str(tmp_path / "tm.json"),
               "--masks", str(tmp_path / "masks.json"), "--out-masks", str(tmp_path / "tmasks.json")])
    assert rc == 0
    tm = read_target_markers(tmp_path / "tm.json", len(v), v)
    assert sorted(tm) == ["corner", "edge", "far", "tip"]
    np.testing.assert_allclose(tm["tip"], v[60], atol=1e-6)
    out = json.loads((tmp_path / "tmasks.json").read_text())
    assert out["note"] == "kept" and out["regions"][0]["exclude_markers"] == ["far"]
    assert out["regions"][0]["vertices"] == lower
    regions = regions_from_masks(read_masks(tmp_path / "tmasks.json"), ["tip", "corner", "edge", "far"], vertices=v)
    assert regions[0].name == "lower" and regions[0].markers == {"tip", "corner", "edge"}
