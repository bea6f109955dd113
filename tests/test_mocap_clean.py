"""Rigid head-motion removal and missing-marker rebuilding (001 section 5)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from keyshape.base.errors import InputError
from keyshape.base.geometry import rigid_fit
from keyshape.retarget.mocap.clean import choose_rigid_set, fill_gaps, rebuild_inner_lips, remove_rigid_motion


def _head(seed=0, n_frames=50, n_rigid=5, n_soft=12):
    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (n_rigid + n_soft, 3))
    soft = np.zeros((n_frames, n_rigid + n_soft, 3))
    soft[:, n_rigid:] = 8 * np.sin(np.linspace(0, 6, n_frames))[:, None, None] * rng.normal(size=(n_soft, 3))
    local = ref + soft
    rot = Rotation.from_rotvec(0.3 * rng.normal(size=(n_frames, 3))).as_matrix()
    trans = rng.normal(0, 30, (n_frames, 3))
    world = np.einsum("fij,fpj->fpi", rot, local) + trans[:, None]
    return world, local, rot, trans


@pytest.mark.parametrize("scale", [False, True])
def test_rigid_fit_batched_recovers_motion(scale):
    world, local, rot, trans = _head()
    s = 1.7 if scale else 1.0
    r, t, sc = rigid_fit(local[0, :5], s * world[:, :5], scale=scale)
    np.testing.assert_allclose(r, rot, atol=1e-10)
    np.testing.assert_allclose(sc, s, atol=1e-10)
    np.testing.assert_allclose(t, s * trans, atol=1e-8)           # s * (R x + t) = s R x + s t
    assert np.allclose(np.linalg.det(r), 1.0)


@pytest.mark.parametrize("named", [True, False])
def test_remove_rigid_motion_named_and_estimated(named):
    world, local, rot, trans = _head(1)
    world[7:12, 2] = np.nan                                  # gaps do not disturb the fit
    rr = remove_rigid_motion(world, rigid=[0, 1, 2, 3, 4] if named else None)
    assert set(rr.rigid.tolist()) <= {0, 1, 2, 3, 4}          # estimated: picks skull markers only
    expect = np.einsum("fpj,ij->fpi", local, rot[0]) + trans[0]   # everything in frame 0's head pose
    expect[7:12, 2] = np.nan
    np.testing.assert_allclose(rr.positions, expect, atol=1e-8)
    assert rr.residual.max() < 1e-8


def test_choose_rigid_set_and_errors():
    world, *_ = _head(2)
    chosen = set(choose_rigid_set(world).tolist())
    assert chosen <= {0, 1, 2, 3, 4} and len(chosen) == 4      # a quarter of 17, all from the skull
    with pytest.raises(InputError, match="at least 3"):
        remove_rigid_motion(world, rigid=[0, 1])
    dead = world.copy()
    dead[:, :5] = np.nan
    with pytest.raises(InputError, match="every marker is missing"):
        remove_rigid_motion(dead, rigid=[0, 1, 2, 3, 4], labels=[f"m{i}" for i in range(17)])
    with pytest.raises(InputError, match="every marker is missing"):
        fill_gaps(np.full((5, 4, 3), np.nan))


def test_fill_gaps_short_long_and_report():
    world, local, *_ = _head(3, n_frames=80, n_soft=0, n_rigid=8)
    x = world.copy()
    x[10:14, 2] = np.nan          # short
    x[30:70, 5] = np.nan          # long
    x[0:3, 6] = np.nan            # at the start
    filled, rep = fill_gaps(x, reference=local[0], max_gap=12, labels=[f"m{i}" for i in range(8)])
    np.testing.assert_allclose(filled, world, atol=1e-8)   # rigid neighbourhoods: rebuilt exactly
    assert [g[0] for g in rep.filled] == ["m2", "m6"]
    assert rep.long == [("m5", 30, 40)]
    assert "long gap: m5 frames 30..69" in str(rep)
    kept, rep2 = fill_gaps(x, reference=local[0], max_gap=12, fill_long=False)
    assert np.isnan(kept[30:70, 5]).all() and len(rep2.long) == 1


def test_fill_gap_meets_the_track_without_a_step():
    world, local, *_ = _head(4, n_frames=60, n_soft=6, n_rigid=6)
    x = world.copy()
    x[20:30, 8] = np.nan
    filled, _ = fill_gaps(x, reference=local[0])
    step = np.linalg.norm(np.diff(filled[18:33, 8], axis=0), axis=1)
    typical = np.linalg.norm(np.diff(world[:, 8], axis=0), axis=1).max()
    assert step.max() <= 1.5 * typical + 1e-9


def test_inner_lip_rebuilt_in_sibling_frame():
    """An inner marker rigidly attached to its outer sibling's neighbourhood is rebuilt exactly."""
    rng = np.random.default_rng(5)
    ref = rng.normal(0, 20, (6, 3))
    ref[4] += 500.0
    n = 30
    rot = Rotation.from_rotvec(0.2 * rng.normal(size=(n, 3))).as_matrix()
    trans = rng.normal(0, 5, (n, 3))
    # markers 0-3 and the inner lip 5 move rigidly together; 4 is far and still
    x = np.repeat(ref[None], n, axis=0)
    grp = [0, 1, 2, 3, 5]
    x[:, grp] = np.einsum("fij,pj->fpi", rot, ref[grp]) + trans[:, None]
    truth = x.copy()
    x[:, 5] = np.nan
    out = rebuild_inner_lips(x, ref, {5: 0}, k=3)
    np.testing.assert_allclose(out, truth, atol=1e-8)


def test_remove_rigid_motion_rejects_a_mislabelled_jig_marker():
    """A jig marker that takes a face marker's place in some frames (a labelling fault) is
    rejected there; the head pose stays exact; clean frames are the least-squares fit bit for bit."""
    world, local, rot, trans = _head(6, n_frames=60, n_rigid=6)
    x = world.copy()
    bad = np.array([4, 18, 19, 41])
    x[bad, 2] = world[bad, 9]                     # label of face marker 9 put on jig marker 2
    x[50, 4] = np.nan
    labels = [f"m{i}" for i in range(x.shape[1])]
    plain = remove_rigid_motion(x, rigid=range(6), outlier_threshold=np.inf)
    rr = remove_rigid_motion(x, rigid=range(6), labels=labels)
    head = np.einsum("fij,kj->fik", rot, rot[0])                  # head_frame_from_ref, ref = frame 0
    assert np.abs(plain.rot[bad] - head[bad]).max() > 1e-2        # the fault tilts the plain fit
    np.testing.assert_allclose(rr.rot, head, atol=1e-9)
    expect = np.einsum("fpj,ij->fpi", local, rot[0]) + trans[0]
    expect[50, 4] = np.nan
    good = np.ones(x.shape[:2], bool)
    good[bad, 2] = False                                          # the faulty samples stay as they were measured
    np.testing.assert_allclose(rr.positions[good], expect[good], atol=1e-7)
    assert rr.rejected_report(labels) == [("m2", 4, 4)]
    assert np.flatnonzero(rr.rejected[:, 2]).tolist() == bad.tolist() and rr.rejected.sum() == 4
    assert rr.residual.max() < 1e-8                              # RMS over the markers kept
    clean = np.setdiff1d(np.arange(len(x)), bad)
    assert np.array_equal(rr.rot[clean], plain.rot[clean])
    assert np.array_equal(rr.positions[clean], plain.positions[clean], equal_nan=True)
    est = remove_rigid_motion(world)                             # estimated set: no rejection by default
    assert not est.rejected.any() and est.threshold == np.inf


def test_clean_take_reports_the_rejected_rigid_marker_by_label():
    from keyshape.retarget.mocap.drive import clean_take
    world, *_ = _head(7, n_frames=30, n_rigid=5)
    x = world.copy()
    x[[3, 8], 1] += 40.0
    labels = [f"m{i}" for i in range(x.shape[1])]
    _, used, _, notes = clean_take(x, labels, rigid_names=["m0", "m1", "m2", "m3", "m4"])
    assert used == ["m0", "m1", "m2", "m3", "m4"]
    assert len(notes) == 1 and notes[0].startswith("rigid set: m1 rejected as an outlier in 2 frame(s), first 3")
    assert clean_take(world, labels, rigid_names=["m0", "m1", "m2", "m3", "m4"])[3] == []
