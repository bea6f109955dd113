"""Key-shape selection and weights (decompose/), on synthetic low-rank tracks with known structure."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls

from keyshape.cli import main
from keyshape.base.errors import InputError, NotFittedError
from keyshape.base.formats.tracks import read_tracks, write_tracks
from keyshape.base.schemes import load_scheme
from keyshape.base.formats.keys import read_keys, write_keys
from keyshape.base.formats.weights import read_weights, write_weights
from keyshape.decompose.regions import decompose_region, model_shapes, region_points, select_region
from keyshape.decompose.selectors import (GreedySelector, HullSelector, KMeansSelector, RandomSelector, SpreadSelector,
                                 make_selector)
from toy import toy_tracks
from keyshape.decompose.weights import (SolveResult, lstsq_weights, nnls_gram, nnls_result, nnls_weights, reconstruct,
                                       smooth_result, smooth_weights,
                               solve_weights)

SCHEME = load_scheme("contours48")


@pytest.fixture(scope="module")
def toy():
    tracks, truth = toy_tracks(300, rng=3, return_truth=True)
    shapes = model_shapes(tracks)
    return tracks, truth, shapes[:, region_points(SCHEME, "mouth")]


def _random_problem(seed, n_frames=200, n_points=12, n_keys=9):
    rng = np.random.default_rng(seed)
    keys = rng.normal(size=(n_keys, n_points, 2))
    neutral = rng.normal(size=(n_points, 2)) * 0.1
    shapes = rng.normal(size=(n_frames, n_points, 2))
    return shapes, keys, neutral


# ----------------------------------------------------------------------------- weights

@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("centred", [True, False], ids=["neutral", "absolute"])
def test_nnls_equals_scipy_lawson_hanson(seed, centred):
    shapes, keys, neutral = _random_problem(seed)
    neutral = neutral if centred else None
    res = nnls_result(shapes, keys, neutral)
    assert isinstance(res, SolveResult) and res.method == "nnls"
    w, ok = res.weights, res.converged
    np.testing.assert_array_equal(w, nnls_weights(shapes, keys, neutral))
    ref_n = 0 if neutral is None else neutral
    B = (keys - ref_n).reshape(len(keys), -1).T
    ref = np.array([nnls(B, x)[0] for x in (shapes - ref_n).reshape(len(shapes), -1)])
    assert ok.all()
    np.testing.assert_allclose(w, ref, atol=1e-9)


def test_nnls_gram_batched_matrices_equal_shared():
    shapes, keys, _ = _random_problem(4, n_keys=6)
    B = keys.reshape(6, -1)
    X = shapes.reshape(len(shapes), -1)
    G = B @ B.T
    w1, _ = nnls_gram(G, X @ B.T)
    w2, ok = nnls_gram(np.broadcast_to(G, (len(X), 6, 6)), X @ B.T)
    assert ok.all()
    np.testing.assert_allclose(w1, w2, atol=1e-12)


def _hard_problem(seed, n_frames=1500, d=40, n_keys=16, cond=1e4):
    """Keys with a chosen condition number; frames a slow random walk of mixed keys plus noise
    (temporal coherence, many weights at zero: exercises the coarse-to-fine warm start)."""
    rng = np.random.default_rng(seed)
    U, _ = np.linalg.qr(rng.normal(size=(d, n_keys)))
    V, _ = np.linalg.qr(rng.normal(size=(n_keys, n_keys)))
    B = (U * np.geomspace(1.0, 1.0 / np.sqrt(cond), n_keys)) @ V.T          # (d, n_keys)
    walk = np.cumsum(rng.normal(scale=0.05, size=(n_frames, n_keys)), axis=0) + rng.normal(size=n_keys)
    X = walk @ B.T + rng.normal(scale=0.05, size=(n_frames, d))
    return B, X


@pytest.mark.parametrize("seed,cond", [(0, 1e2), (1, 1e4), (2, 1e6)])
def test_nnls_gram_equals_scipy_on_ill_conditioned_sequences(seed, cond):
    B, X = _hard_problem(seed, cond=cond)
    G, h = B.T @ B, X @ B
    w, ok = nnls_gram(G, h)
    assert ok.all() and w.min() >= 0.0
    assert 0.1 < (w == 0).mean() < 0.9                     # the constraints matter
    ref = np.array([nnls(B, x, maxiter=2000)[0] for x in X])
    np.testing.assert_allclose(w, ref, atol=1e-9 * max(1.0, np.abs(ref).max()))
    # the result does not depend on the row order (only the warm start's speed does)
    perm = np.random.default_rng(seed).permutation(len(X))
    w_perm, _ = nnls_gram(G, h[perm])
    np.testing.assert_allclose(w_perm, w[perm], atol=1e-12 * max(1.0, np.abs(ref).max()))
    w_cold, _ = nnls_gram(G, h, coarse=1)
    np.testing.assert_allclose(w_cold, w, atol=1e-12 * max(1.0, np.abs(ref).max()))


@pytest.mark.parametrize("case", ["duplicate_keys", "more_keys_than_dims", "zero_key"])
def test_nnls_rank_deficient_reaches_scipys_residual(case):
    # the minimiser is not unique here: compare the residual (unique), not the weights
    rng = np.random.default_rng(5)
    d, k = 12, 8
    B = rng.normal(size=(d, k))
    if case == "duplicate_keys":
        B[:, 3] = B[:, 1]
        B[:, 6] = 2.0 * B[:, 0]
    elif case == "more_keys_than_dims":
        B = rng.normal(size=(5, k))
        d = 5
    else:
        B[:, 2] = 0.0
    X = np.cumsum(rng.normal(size=(600, d)), axis=0) * 0.3
    w, ok = nnls_gram(B.T @ B, X @ B)
    assert ok.all() and w.min() >= 0.0 and np.isfinite(w).all()
    r_ours = np.linalg.norm(w @ B.T - X, axis=1)
    r_ref = np.array([nnls(B, x, maxiter=2000)[1] for x in X])
    np.testing.assert_allclose(r_ours, r_ref, rtol=1e-9, atol=1e-9)


@settings(max_examples=60, deadline=None)
@example(seed=2301282, n_keys=6, n_dims=4, n_frames=1, log_cond=0.0)  # nearly dependent keys, weights ~2,300
@given(seed=st.integers(0, 2**32 - 1), n_keys=st.integers(1, 10), n_dims=st.integers(1, 14),
       n_frames=st.integers(1, 300), log_cond=st.floats(0.0, 5.0))
def test_nnls_gram_property_kkt_and_scipy(seed, n_keys, n_dims, n_frames, log_cond):
    """Any basis (rank-deficient too), any frames: KKT holds, the residual is scipy's, and where
    the basis has full column rank the weights are scipy's."""
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(n_dims, n_keys)) * np.geomspace(1.0, 10.0 ** -log_cond, n_keys)
    X = np.cumsum(rng.normal(size=(n_frames, n_dims)), axis=0) * 0.2 + rng.normal(size=n_dims)
    w, ok = nnls_gram(B.T @ B, X @ B, coarse=4)
    assert ok.all() and w.min() >= 0.0
    ref = [nnls(B, x, maxiter=50 * n_keys) for x in X]
    r_ref = np.array([r[1] for r in ref])
    # the Gram matrix squares the basis' condition number: where nearly dependent keys give huge
    # weights (a hypothesis case: 6 keys in 4 dimensions, weights ~2,300) the residual agrees
    # to 1e-9 of the weights' size times the basis norm, not absolutely
    tol = 1e-8 * max(1.0, float(np.abs(X).max())) + 1e-9 * float(np.abs(w).max()) * float(np.linalg.norm(B, 2))
    np.testing.assert_allclose(np.linalg.norm(w @ B.T - X, axis=1), r_ref, rtol=1e-8, atol=tol)
    s = np.linalg.svd(B, compute_uv=False)
    if n_dims >= n_keys and s[-1] > 1e-3 * s[0]:
        wr = np.array([r[0] for r in ref])
        np.testing.assert_allclose(w, wr, atol=1e-9 * max(1.0, np.abs(wr).max()))


@pytest.mark.parametrize("seed", range(5))
def test_nnls_weights_never_negative(seed):
    shapes, keys, neutral = _random_problem(seed + 10, n_keys=int(5 + seed * 3))
    assert nnls_weights(shapes, keys, neutral).min() >= 0.0
    assert smooth_weights(shapes, keys, neutral, smooth_lambda=0.5).min() >= 0.0
    assert lstsq_weights(shapes, keys, neutral).min() < 0  # the unconstrained solution does go negative


def test_ridge_zero_is_the_paper_and_ridge_shrinks_weights():
    shapes, keys, neutral = _random_problem(21, n_keys=7)
    for solver in ("nnls", "lstsq"):
        w0 = solve_weights(shapes, keys, neutral, solver=solver)
        np.testing.assert_array_equal(solve_weights(shapes, keys, neutral, solver=solver, ridge=0.0), w0)
        norms = [np.linalg.norm(solve_weights(shapes, keys, neutral, solver=solver, ridge=r)) for r in (0, 0.1, 1)]
        assert norms[0] > norms[1] > norms[2], (solver, norms)
    # ridge NNLS = NNLS of the system augmented with sqrt(ridge * trace(G) / k) * I rows (scipy's Lawson-Hanson)
    r = 0.2
    B = (keys - neutral).reshape(len(keys), -1).T
    a = np.sqrt(r * (B ** 2).sum() / len(keys))
    aug = np.vstack([B, a * np.eye(len(keys))])
    ref = np.array([nnls(aug, np.r_[x, np.zeros(len(keys))])[0] for x in (shapes - neutral).reshape(len(shapes), -1)])
    w = nnls_weights(shapes, keys, neutral, ridge=r)
    assert w.min() >= 0
    np.testing.assert_allclose(w, ref, atol=1e-9)
    ridge_ls = np.linalg.lstsq(aug, np.vstack([(shapes - neutral).reshape(len(shapes), -1).T,
                                               np.zeros((len(keys), len(shapes)))]), rcond=None)[0].T
    np.testing.assert_allclose(lstsq_weights(shapes, keys, neutral, ridge=r), ridge_ls, atol=1e-9)
    # the smooth solver with no smoothing is ridge NNLS too
    np.testing.assert_allclose(smooth_weights(shapes, keys, neutral, 0.0, ridge=r), w, atol=1e-9)
    with pytest.raises(InputError, match="ridge"):
        nnls_weights(shapes, keys, neutral, ridge=-1.0)


@pytest.mark.parametrize("solver", ["nnls", "lstsq"])
def test_key_shapes_decompose_exactly_into_themselves(toy, solver):
    _, _, Q = toy
    sel = SpreadSelector(10).fit(Q)
    w = solve_weights(sel.keys_, sel.keys_, sel.neutral_, solver=solver)
    np.testing.assert_allclose(w, np.eye(10), atol=1e-8)
    np.testing.assert_allclose(reconstruct(w, sel.keys_, sel.neutral_), sel.keys_, atol=1e-8)


def test_frame_equal_to_key_uses_that_key_alone(toy):
    _, _, Q = toy
    sel = SpreadSelector(8).fit(Q)
    frames = Q[sel.indices_[[2, 5]]]
    w = nnls_weights(frames, sel.keys_, sel.neutral_)
    expect = np.zeros((2, 8))
    expect[0, 2] = expect[1, 5] = 1.0
    np.testing.assert_allclose(w, expect, atol=1e-8)


def test_smooth_with_zero_lambda_is_nnls(toy):
    _, _, Q = toy
    sel = SpreadSelector(8).fit(Q)
    obs = np.ones(len(Q), bool)
    obs[[5, 50]] = False
    w0 = smooth_weights(np.where(obs[:, None, None], Q, sel.neutral_), sel.keys_, sel.neutral_, 0.0,
                        observed=obs, tol=1e-10)
    np.testing.assert_allclose(w0[obs], nnls_weights(Q[obs], sel.keys_, sel.neutral_), atol=1e-6)


@pytest.mark.parametrize("seed", [5, 6])
def test_smooth_halves_jitter_on_static_stretches_with_small_error_cost(seed):
    tracks, truth = toy_tracks(600, noise_px=1.0, rng=seed, return_truth=True)
    Q = model_shapes(tracks)[:, region_points(SCHEME, "mouth")]
    sel = SpreadSelector(12).fit(Q)
    still = truth["static"][1:] & truth["static"][:-1]
    res = {}
    for solver in ("nnls", "smooth"):
        w = solve_weights(Q, sel.keys_, sel.neutral_, solver=solver)  # default smooth_lambda
        jitter = np.sqrt((np.diff(w, axis=0)[still] ** 2).sum(1).mean())
        err = np.sqrt(((reconstruct(w, sel.keys_, sel.neutral_) - Q) ** 2).sum(-1).mean())
        res[solver] = jitter, err
    assert res["smooth"][0] < 0.5 * res["nnls"][0], res
    assert res["smooth"][1] < 1.10 * res["nnls"][1], res


def test_failed_frames_interpolated():
    w_obs = np.array([[0.0, 1.0], [1.0, 3.0]])
    obs = np.array([False, True, False, False, True, False])
    shapes = np.zeros((6, 3, 2))
    from keyshape.decompose.weights import interpolate_rows
    w = interpolate_rows(w_obs, obs)
    np.testing.assert_allclose(w[:, 0], [0, 0, 1 / 3, 2 / 3, 1, 1])
    np.testing.assert_allclose(w[:, 1], [1, 1, 5 / 3, 7 / 3, 3, 3])
    assert shapes.shape == (6, 3, 2)


def test_nan_shapes_are_an_error():
    shapes, keys, neutral = _random_problem(0)
    shapes[3, 1, 0] = np.nan
    with pytest.raises(InputError, match="NaN.*frame rows \\[3\\]"):
        nnls_weights(shapes, keys, neutral)
    with pytest.raises(InputError, match="NaN"):
        SpreadSelector(4).fit(shapes)


# ----------------------------------------------------------------------------- selectors

def test_spread_picks_extremes_of_principal_axes(toy):
    _, _, Q = toy
    X = (Q - Q.mean(0)).reshape(len(Q), -1)
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    p1 = X @ Vt[0]
    sel = SpreadSelector(6).fit(Q)
    assert set(sel.indices_[:2]) == {int(np.argmax(p1)), int(np.argmin(p1))}
    assert len(set(sel.indices_)) == 6
    np.testing.assert_array_equal(SpreadSelector(4).fit(Q).indices_, sel.indices_[:4])  # nested


@pytest.mark.parametrize("method", ["spread", "kmeans2", "kmeans3", "random", "greedy"])
def test_selector_interface(toy, method):
    _, _, Q = toy
    sel = make_selector(method, 7, rng=0)
    with pytest.raises(NotFittedError, match="not fitted"):
        sel.n_keys_
    assert sel.fit(Q) is sel
    assert sel.indices_.shape == (7,) and sel.keys_.shape == (7, *Q.shape[1:])
    assert len(set(sel.indices_.tolist())) == 7 and sel.indices_.max() < len(Q)
    again = make_selector(method, 7, rng=0).fit(Q)
    np.testing.assert_array_equal(again.indices_, sel.indices_)   # seeded: reproducible
    with pytest.raises(InputError, match="cannot choose 400 key shapes from 300 frames"):
        make_selector(method, 400, rng=0).fit(Q)


def test_kmeans_centre_mean_and_nearest(toy):
    _, _, Q = toy
    mean = KMeansSelector(5, n_dims=2, centre="mean", rng=1).fit(Q)
    near = KMeansSelector(5, n_dims=2, centre="nearest", rng=1).fit(Q)
    np.testing.assert_array_equal(mean.indices_, near.indices_)
    np.testing.assert_allclose(near.keys_, Q[near.indices_])
    assert not np.allclose(mean.keys_, near.keys_)
    # centres of mass average the shapes: inside the range of the data
    assert (mean.keys_.min(0) >= Q.min(0) - 1e-9).all() and (mean.keys_.max(0) <= Q.max(0) + 1e-9).all()


def test_hull_selects_the_2d_hull_vertices(toy):
    from scipy.spatial import Delaunay

    _, _, Q = toy
    sel = HullSelector().fit(Q)
    X = (Q - Q.mean(0)).reshape(len(Q), -1)
    Vt = np.linalg.svd(X, full_matrices=False)[2]
    Y = X @ Vt[:2].T
    inside = Delaunay(Y[sel.indices_]).find_simplex(Y) >= 0
    assert inside.all() and 3 <= len(sel.indices_) < len(Q) // 2


@pytest.mark.parametrize("n_dims", [2, 3])
def test_kmeans_recovers_known_clusters(n_dims):
    """Shapes drawn around 5 known expressions (well apart, small noise): k-means with k = 5 puts each
    expression in its own cluster, its key (centre of mass) is that expression's mean, and the
    nearest-frame index is a member of that cluster."""
    rng = np.random.default_rng(5)
    protos = rng.normal(scale=10.0, size=(5, 12, 2))
    truth = rng.integers(0, 5, size=200)
    truth[:5] = np.arange(5)                                     # every cluster populated
    Q = protos[truth] + rng.normal(scale=0.3, size=(200, 12, 2))
    sel = KMeansSelector(5, n_dims=n_dims, centre="mean", rng=0).fit(Q)
    found = truth[sel.indices_]
    assert sorted(found.tolist()) == [0, 1, 2, 3, 4]             # one key per true cluster
    for key, c in zip(sel.keys_, found):
        np.testing.assert_allclose(key, Q[truth == c].mean(0), atol=1e-9)


def test_random_selector_uses_rng(toy):
    _, _, Q = toy
    a = RandomSelector(6, rng=1).fit(Q).indices_
    b = RandomSelector(6, rng=2).fit(Q).indices_
    assert not np.array_equal(a, b)


def test_greedy_beats_spread_by_20_percent():
    tracks = toy_tracks(300, rng=7)
    Q = model_shapes(tracks)[:, region_points(SCHEME, "mouth")]
    g = GreedySelector(12, rng=0).fit(Q)
    for k in (8, 12):
        sp = SpreadSelector(k).fit(Q)
        e = []
        for keys in (sp.keys_, Q[g.order_[:k]]):
            w = nnls_weights(Q, keys, Q.mean(0))
            e.append(np.sqrt(((reconstruct(w, keys, Q.mean(0)) - Q) ** 2).mean()))
        assert e[1] < 0.8 * e[0], (k, e)


# ----------------------------------------------------------------------------- regions and failed frames

def test_failed_frames_never_selected_and_weights_flagged(tmp_path):
    tracks = toy_tracks(200, rng=2, fail_fraction=0.1)
    failed = set(tracks.frame[~tracks.success].tolist())
    for method in ("spread", "greedy", "random", "kmeans2"):
        rk = select_region(tracks, SCHEME, "mouth", 6, method, rng=0)
        assert not failed & set(rk.frames.tolist()), method
    rk = select_region(tracks, SCHEME, "eyes", 6)
    w = decompose_region(tracks, rk, "nnls")
    assert np.isfinite(w).all() and w.min() >= 0
    t = np.flatnonzero(~tracks.success)[0]
    if 0 < t < len(w) - 1 and tracks.success[t - 1] and tracks.success[t + 1]:
        np.testing.assert_allclose(w[t], (w[t - 1] + w[t + 1]) / 2)


def test_pose_is_removed_before_selection():
    tracks, truth = toy_tracks(100, noise_px=0.0, rng=1, return_truth=True)
    np.testing.assert_allclose(model_shapes(tracks), truth["shapes"], atol=1e-9)


def test_region_errors():
    tracks = toy_tracks(50, rng=0)
    with pytest.raises(InputError, match="lacks region.*pupils"):
        region_points(load_scheme("ibug68"), "pupils")
    with pytest.raises(InputError, match="unknown region 'nose'"):
        region_points(SCHEME, "nose")
    with pytest.raises(InputError, match="cannot choose 60 key shapes from 50 successful frames"):
        select_region(tracks, SCHEME, "mouth", 60)
    tracks.points[4, 3] = np.nan
    with pytest.raises(InputError, match="frames \\[4\\] are marked success=1"):
        model_shapes(tracks)


# ----------------------------------------------------------------------------- formats

def test_keys_and_weights_round_trip(tmp_path):
    tracks = toy_tracks(80, rng=0)
    regs = [select_region(tracks, SCHEME, r, 5, m, rng=0) for r, m in (("mouth", "spread"), ("eyes", "kmeans2"))]
    write_keys(tmp_path / "k.json", "contours48", 48, regs)
    name, n, back = read_keys(tmp_path / "k.json")
    assert (name, n) == ("contours48", 48)
    for a, b in zip(regs, back):
        assert a.region == b.region and a.method == b.method and b.names == [f"{a.region}_{i}" for i in range(5)]
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.frames, b.frames)
        np.testing.assert_array_equal(a.from_frame, b.from_frame)
        np.testing.assert_allclose(a.keys, b.keys, atol=1e-6)
        np.testing.assert_allclose(a.neutral, b.neutral, atol=1e-6)
    assert not back[1].from_frame.any()        # kmeans centres of mass are not frames
    w = np.random.default_rng(0).random((80, 10))
    flag = np.zeros(80, bool)
    flag[3] = True
    write_weights(tmp_path / "w.csv", tracks.frame, back[0].names + back[1].names, w, flag)
    fr, names, w2, fl = read_weights(tmp_path / "w.csv")
    assert names[0] == "mouth_0" and names[-1] == "eyes_4"
    np.testing.assert_array_equal(fr, tracks.frame)
    np.testing.assert_allclose(w2, w, atol=1e-6)
    np.testing.assert_array_equal(fl, flag)


def test_format_errors_name_the_file(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{}")
    with pytest.raises(InputError, match="bad.json.*not a key-shapes file"):
        read_keys(p)
    p.write_text(json.dumps({"format": "keyshape-keys", "scheme": "contours48", "n_points": 48,
                             "regions": {"mouth": {"points": [0, 1], "neutral": [[0, 0]], "keys": []}}}))
    with pytest.raises(InputError, match="bad.json.*no key shapes"):
        read_keys(p)
    q = tmp_path / "w.csv"
    q.write_text("frame,mouth_0,blob\n0,1,2\n")
    with pytest.raises(InputError, match="w.csv.*REGION_K"):
        read_weights(q, key_names=True)
    q.write_text("frame,mouth_0\n0,x\n")
    with pytest.raises(InputError, match="w.csv, line 2"):
        read_weights(q)


# ----------------------------------------------------------------------------- commands

def test_cli_select_decompose_compare(tmp_path, capsys):
    tracks = toy_tracks(150, rng=4, fail_fraction=0.05)
    write_tracks(tmp_path / "t.csv", tracks)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "6", "--method", "greedy", "--region", "mouth",
                 "--region", "eyes", "-o", str(tmp_path / "k.json")]) == 0
    assert main(["decompose", str(tmp_path / "t.csv"), "--keys", str(tmp_path / "k.json"), "--solver", "smooth",
                 "-o", str(tmp_path / "w.csv")]) == 0
    fr, names, w, flag = read_weights(tmp_path / "w.csv", key_names=True)
    np.testing.assert_array_equal(fr, tracks.frame)
    assert names == [f"mouth_{i}" for i in range(6)] + [f"eyes_{i}" for i in range(6)]
    np.testing.assert_array_equal(flag, ~tracks.success)
    assert w.min() >= 0
    assert main(["compare", str(tmp_path / "t.csv"), "--kmax", "5", "--methods", "spread", "random", "hull2",
                 "--region", "mouth", "-o", str(tmp_path / "cmp")]) == 0
    lines = (tmp_path / "cmp" / "errors.csv").read_text().splitlines()
    assert lines[0].startswith("method,region,k,error,rms_px,target_nnls_px,target_lstsq_px")
    assert len(lines) == 1 + 4 + 4 + 1
    assert (tmp_path / "cmp" / "errors.png").stat().st_size > 1000


def test_cli_errors_are_one_line(tmp_path, capsys):
    tracks = toy_tracks(30, rng=0)
    tracks.points[2, 0] = np.nan
    write_tracks(tmp_path / "t.csv", tracks)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "4", "-o", str(tmp_path / "k.json")]) == 2
    assert "t.csv: frames [2] are marked success=1" in capsys.readouterr().err
    tracks = toy_tracks(30, rng=0)
    write_tracks(tmp_path / "t.csv", tracks)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "40", "-o", str(tmp_path / "k.json")]) == 2
    assert "cannot choose 40 key shapes from 30" in capsys.readouterr().err
    assert main(["select", str(tmp_path / "t.csv"), "-k", "4", "--region", "nose", "-o", "x.json"]) == 2
    assert not (tmp_path / "k.json").exists()


def test_sheet_draws_key_frames(tmp_path, capsys):
    import cv2

    from keyshape.base.formats.video import video_writer

    tracks = toy_tracks(40, rng=0)
    tracks.points *= 0.8   # keep the face inside a 320x240 frame
    tracks.pose[:, :, :] *= 0.8
    with video_writer(tmp_path / "v.mp4", 25, (320, 240)) as wr:
        for t in range(40):
            wr.write(np.full((240, 320, 3), 40 + t, np.uint8))
    write_tracks(tmp_path / "t.csv", tracks)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "4", "--region", "mouth", "-o", str(tmp_path / "k.json"),
                 "--sheet", str(tmp_path / "s.png"), "--video", str(tmp_path / "v.mp4")]) == 0
    img = cv2.imread(str(tmp_path / "s.png"))
    assert img is not None and img.shape[1] > 4 * 280
    assert (img[..., 1].astype(int) - img[..., 0] > 100).any()   # green lip contours drawn
    (tmp_path / "bad.mp4").write_bytes(b"not a video")             # the sheet's own bad input fails cleanly
    assert main(["select", str(tmp_path / "t.csv"), "-k", "4", "--region", "mouth", "-o", str(tmp_path / "k2.json"),
                 "--sheet", str(tmp_path / "s2.png"), "--video", str(tmp_path / "bad.mp4")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.mp4" in err[0] and not (tmp_path / "s2.png").exists()


# ----------------------------------------------------------------------------- target-domain check

def test_compare_rows_do_not_depend_on_the_number_of_worker_processes(toy):
    """compare runs each (region, method) as a job with its own random stream: the same rows (random,
    k-means and greedy included) in one process or in several."""
    from keyshape.decompose.compare import compare

    tracks = toy[0]
    one = compare(tracks, SCHEME, regions=["mouth", "eyes"], kmin=2, kmax=5, rng=7, workers=1)
    two = compare(tracks, SCHEME, regions=["mouth", "eyes"], kmin=2, kmax=5, rng=7, workers=2)
    assert len(one) == 2 * (5 * 4 + 1) and one == two
    other = compare(tracks, SCHEME, regions=["mouth", "eyes"], kmin=2, kmax=5, rng=8, workers=1)
    assert [r["rms_px"] for r in other if r["method"] == "random"] != [r["rms_px"] for r in one
                                                                      if r["method"] == "random"]


def test_compare_reused_factorisation_equals_direct_solves(toy):
    """compare's per-k leading blocks (one Gram / one QR at kmax) give the weights of solving each k
    afresh, also where k exceeds the region's coordinates (pupils: 2 points, 4 numbers)."""
    from keyshape.decompose.compare import _Basis

    _, _, Q = toy
    sel = SpreadSelector(8).fit(Q)
    b = _Basis(Q, Q[sel.order_], Q.mean(0))
    for k in (2, 5, 8):
        keys = Q[sel.order_[:k]]
        np.testing.assert_allclose(b.nnls(k), nnls_weights(Q, keys, Q.mean(0)), atol=1e-8)
        np.testing.assert_allclose(b.lstsq(k), lstsq_weights(Q, keys, Q.mean(0)), atol=1e-8)
    tracks = toy[0]
    pupils = region_points(SCHEME, "pupils")
    Qp = model_shapes(tracks)[:, pupils]
    bp = _Basis(Qp, Qp[:6], Qp.mean(0))
    w = bp.lstsq(6)                                   # 6 keys, 4 coordinates: minimum-norm solution
    np.testing.assert_allclose(w, np.linalg.lstsq((Qp[:6] - Qp.mean(0)).reshape(6, -1).T,
                                                  (Qp - Qp.mean(0)).reshape(len(Qp), -1).T, rcond=None)[0].T)
    assert bp.nnls(6).min() >= 0.0


def test_target_domain_measures(toy):
    from keyshape.decompose.compare import compare, smooth_field

    tracks, _, Q = toy
    scheme = SCHEME
    # no perturbation: the target-domain error is the source reconstruction error, independent key errors nil
    for row in compare(tracks, scheme, methods=["spread"], regions=["mouth"], kmin=6, kmax=6, amplitude=0.0, rng=0):
        assert row["target_nnls_px"] == pytest.approx(row["rms_px"])
        assert row["keynoise_nnls_px"] == pytest.approx(0.0, abs=1e-9)
    # the field has the amplitude asked (RMS over the points it was scaled on)
    f = smooth_field(Q.reshape(-1, 2), 2.0, rng=1)
    d = f(Q.reshape(-1, 2)) - Q.reshape(-1, 2)
    assert np.sqrt((d ** 2).sum(-1).mean()) == pytest.approx(2.0, rel=1e-6)
    # weights of both signs amplify independent key errors; NNLS on the same keys does not
    row = compare(tracks, scheme, methods=["spread"], regions=["mouth"], kmin=10, kmax=10, amplitude=2.0, rng=3)[0]
    assert row["keynoise_lstsq_px"] > row["keynoise_nnls_px"]


@pytest.mark.slow
def test_on_synthetic_video_truth(tmp_path):
    """Greedy >= 20% below spread at k = 8, 12, 16 and NNLS below lstsq on independent key errors."""
    from keyshape.data_synth.video import synthesize
    from keyshape.decompose.compare import compare

    paths = synthesize(tmp_path / "s", frames=300, seed=0, labels=1)
    tracks = read_tracks(paths["truth"])
    rows = compare(tracks, SCHEME, methods=("spread", "greedy"), regions=("mouth",), kmin=8, kmax=16, rng=0)
    by = {(r["method"], r["k"]): r for r in rows}
    for k in (8, 12, 16):
        assert by[("greedy", k)]["rms_px"] < 0.8 * by[("spread", k)]["rms_px"], k
    for k in range(8, 17):
        assert by[("spread", k)]["keynoise_nnls_px"] < by[("spread", k)]["keynoise_lstsq_px"], k


def _smooth_reference(shapes, keys, neutral, lam, observed):
    """The smoothed-NNLS QP as one NNLS problem ``min_{w >= 0} ||A w - b||``, solved exactly by
    scipy's Lawson-Hanson (independent of the ADMM solver)."""
    X = (shapes - neutral).reshape(len(shapes), -1)
    B = (keys - neutral).reshape(len(keys), -1)
    n, k = len(X), len(B)
    mu = lam * float(np.trace(B @ B.T)) / k
    A = np.zeros((n * X.shape[1] + (n - 1) * k, n * k))
    b = np.zeros(len(A))
    d = X.shape[1]
    for t in range(n):
        if observed[t]:
            A[t * d:(t + 1) * d, t * k:(t + 1) * k] = B.T
            b[t * d:(t + 1) * d] = X[t]
    r0 = n * d
    for t in range(1, n):
        A[r0 + (t - 1) * k + np.arange(k), t * k + np.arange(k)] = np.sqrt(mu)
        A[r0 + (t - 1) * k + np.arange(k), (t - 1) * k + np.arange(k)] = -np.sqrt(mu)
    x, rnorm = nnls(A, b, maxiter=50 * A.shape[1])
    return x.reshape(n, k), float(rnorm ** 2)


@pytest.mark.parametrize("method", ["pdas", "admm"])
@pytest.mark.parametrize("partial", [False, True])
def test_smooth_matches_tight_bounded_least_squares(partial, method):
    # both solvers of the smoothed QP: the active-set method (the default) and ADMM (its fallback should
    # a factorisation fail or the active set stop shrinking), against the exact QP (scipy's NNLS)
    # 120 frames x 5 keys; weights that often touch zero so the bounds are active
    rng = np.random.default_rng(11)
    n, k = 120, 5
    neutral = rng.normal(size=(10, 2))
    keys = neutral + rng.normal(size=(k, 10, 2))
    t = np.arange(n)[:, None]
    w_true = np.maximum(np.sin(t / 15.0 + np.arange(k)) * 0.8, 0.0)
    shapes = neutral + np.einsum("tk,kpd->tpd", w_true, keys - neutral) + rng.normal(scale=0.3, size=(n, 10, 2))
    obs = np.ones(n, bool)
    if partial:
        obs[[0, 1, 40, 41, 42, 43, 90, n - 1]] = False
    ref, f_ref = _smooth_reference(shapes, keys, neutral, 0.1, obs)
    assert (ref < 1e-9).mean() > 0.1  # the constraints matter
    filled = np.where(obs[:, None, None], shapes, neutral)
    X = (filled - neutral).reshape(n, -1)
    B = (keys - neutral).reshape(k, -1)
    mu = 0.1 * float(np.trace(B @ B.T)) / k

    def objective(w):
        r = w @ B - X
        return float((obs * np.sum(r * r, axis=1)).sum() + mu * np.sum(np.diff(w, axis=0) ** 2))

    res_ = smooth_result(filled, keys, neutral, 0.1, observed=obs, tol=1e-10, max_iter=20000, method=method)
    tight = res_.weights
    assert isinstance(res_, SolveResult) and res_.converged.all() and res_.method == method
    assert tight.min() >= 0.0
    np.testing.assert_allclose(tight, ref, atol=1e-6)
    res_ = smooth_result(filled, keys, neutral, 0.1, observed=obs, method=method)  # default tol 1e-5
    w = res_.weights
    np.testing.assert_array_equal(w, smooth_weights(filled, keys, neutral, 0.1, observed=obs, method=method))
    assert res_.converged.all() and w.min() >= 0.0
    assert np.abs(w - ref).max() < 1e-2 and np.sqrt(np.mean((w - ref) ** 2)) < 2e-3
    assert objective(w) <= f_ref * (1 + 1e-5) and abs(objective(ref) - f_ref) < 1e-8 * f_ref


def test_head_pose_is_the_nearest_similarity_and_model_shapes_round_trip():
    from keyshape.decompose.regions import head_pose, to_image
    rng = np.random.default_rng(5)
    tracks = toy_tracks(40, noise_px=0.5, rng=2)
    sim = tracks.pose.copy()
    np.testing.assert_allclose(head_pose(sim), sim, atol=1e-12)          # a similarity is kept as it is
    # the tracker's affine: similarity x (shear, anisotropic scale)
    tracks.pose[:, :, :2] = np.einsum("tij,tjk->tik", sim[:, :, :2], np.eye(2) + 0.05 * rng.normal(size=(40, 2, 2)))
    S = head_pose(tracks.pose)
    np.testing.assert_allclose(S[:, :, 2], tracks.pose[:, :, 2])
    D = tracks.pose[:, :, :2] - S[:, :, :2]                              # orthogonal to every similarity
    for M in (np.eye(2), np.array([[0.0, -1.0], [1.0, 0.0]])):
        np.testing.assert_allclose(np.einsum("tij,ij->t", D, M), 0, atol=1e-12)
    assert np.allclose(S[:, 0, 0], S[:, 1, 1]) and np.allclose(S[:, 0, 1], -S[:, 1, 0])
    # model shapes and to_image use the same head pose: the tracked points come back exactly
    np.testing.assert_allclose(to_image(model_shapes(tracks), tracks.pose)[tracks.success],
                               tracks.points[tracks.success], atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(2, 9), st.integers(1, 60), st.sampled_from([0.01, 0.1, 1.0]),
       st.booleans(), st.sampled_from([0.0, 0.05]))
def test_smooth_active_set_solution_satisfies_kkt(seed, k, n, lam, partial, ridge):
    # the active-set (PDAS) smooth solver ends at the KKT point of its QP: w >= 0, the gradient of the
    # objective zero on positive weights and >= 0 on zero weights (to rounding), on random problems
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(6, 2))
    keys = neutral + rng.normal(size=(k, 6, 2))
    shapes = neutral + rng.normal(size=(n, 6, 2))
    obs = rng.random(n) > 0.3 if partial else np.ones(n, bool)
    obs[rng.integers(n)] = True
    res_ = smooth_result(np.where(obs[:, None, None], shapes, neutral), keys, neutral, lam, observed=obs,
                         tol=1e-10, ridge=ridge)
    w = res_.weights
    assert res_.converged.all() and res_.method == "pdas"
    assert w.min() >= 0.0
    X = (shapes - neutral).reshape(n, -1)
    B = (keys - neutral).reshape(k, -1)
    G = B @ B.T
    mu = lam * float(np.trace(G)) / k
    Gr = G + ridge * float(np.trace(G)) / k * np.eye(k)
    grad = obs[:, None] * (w @ Gr - X @ B.T)
    d = np.diff(w, axis=0) * mu
    grad[:-1] -= d
    grad[1:] += d
    scale = float(np.trace(G)) / k * max(1.0, np.abs(w).max())
    assert np.abs(grad[w > 0]).max(initial=0.0) < 1e-7 * scale
    assert grad[w == 0].min(initial=0.0) > -1e-7 * scale


def test_smooth_active_set_does_not_cycle_on_failed_frames():
    # toy tracks where plain PDAS exchanged one frame's weights back and forth forever (the solver
    # fell back to ADMM); the single-exchange backup rule ends at the KKT point
    Q = model_shapes(toy_tracks(1500, noise_px=1.0, rng=3))
    sel = RandomSelector(16, rng=0).fit(Q)
    obs = np.ones(len(Q), bool)
    obs[100:140] = False
    obs[700] = False
    F = np.where(obs[:, None, None], Q, sel.neutral_)
    res_ = smooth_result(F, sel.keys_, sel.neutral_, 0.01, observed=obs, tol=1e-10)
    w = res_.weights
    assert res_.converged.all() and res_.method == "pdas", res_.method
    X = (Q - sel.neutral_).reshape(len(Q), -1)
    B = (sel.keys_ - sel.neutral_).reshape(16, -1)
    G = B @ B.T
    grad = obs[:, None] * (w @ G - X @ B.T)
    d = np.diff(w, axis=0) * 0.01 * float(np.trace(G)) / 16
    grad[:-1] -= d
    grad[1:] += d
    scale = float(np.trace(G)) / 16 * max(1.0, w.max())
    assert w.min() >= 0 and np.abs(grad[w > 0]).max() < 1e-7 * scale and grad[w == 0].min() > -1e-7 * scale


def test_smooth_falls_back_to_admm_and_still_solves_the_qp(monkeypatch):
    # should the active-set method stop short, ADMM takes over from the per-frame start: same QP solution
    import keyshape.decompose.weights as wmod

    rng = np.random.default_rng(4)
    n, k = 60, 4
    neutral = rng.normal(size=(8, 2))
    keys = neutral + rng.normal(size=(k, 8, 2))
    shapes = neutral + rng.normal(scale=0.7, size=(n, 8, 2))
    obs = np.ones(n, bool)
    ref, _ = _smooth_reference(shapes, keys, neutral, 0.1, obs)
    monkeypatch.setattr(wmod, "_smooth_pdas", lambda Gs, H, m, mu, W, max_iter, tol: (W, max_iter, False))
    res_ = smooth_result(shapes, keys, neutral, 0.1, tol=1e-10, max_iter=20000)
    w = res_.weights
    assert res_.method == "pdas, then admm" and res_.converged.all()
    np.testing.assert_allclose(w, ref, atol=1e-6)
