"""Issue 14 acceptance (slow): a synthetic take through the default chain onto the full ICT-FaceKit rig.

Seed 11 (no other test uses it), 600 frames. From the exact contours (truth.csv) the pose route
must recover the hidden ARKit curves (r >= 0.9 for jawOpen and both blinks, mean r >= 0.8, rig
vertex error <= 0.65 x the hidden motion). From the trained tracker's tracks (this code, with the
lips' shared stretch and tilt: jawOpen 0.902, blinks 0.895 / 0.921, mean r 0.819, rig vertex error
0.670 x) jawOpen, eyeBlink_R and the mean r are met, eyeBlink_L and the vertex error are not; before
the tracker changes merged with f9ca570 the same chain gave 0.906 / 0.907 / 0.933 / 0.867 / 0.660,
between the two 0.874 / 0.895 / 0.921 / 0.883 / 0.718. The mouth's pose fit is the loss (0.671 x with
only the mouth's shapes fitted), much of it an amplitude difference between the synthetic face and
the ICT head that no 2D fit can see (jawOpen's 2D motion is made by ICT's jawOpen at 0.44; a perfect
2D pose fit would leave 0.490 x): see ``bench/rig_accuracy.py`` and the README. The tracked run is
held to a regression floor and the issue's targets are a strict xfail, so meeting them is noticed.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def chain(tmp_path_factory, shared_data):
    import importlib.util
    from pathlib import Path
    spec = importlib.util.spec_from_file_location("rig_accuracy", Path(__file__).parents[1] / "bench" /
                                                  "rig_accuracy.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    from keyshape.retarget.rig import load_rig
    rigdir = shared_data / "ict-facekit"
    rig = load_rig(rigdir, with_mesh=False)
    work = tmp_path_factory.mktemp("rig_acceptance")
    tracked = bench.score(bench.run_chain(work, 11, rigdir), rig)
    exact = bench.score(bench.run_chain(work, 11, rigdir, tracks=work / "take" / "truth.csv"), rig)
    print(bench.table({"tracked": tracked, "exact contours": exact}))
    return tracked, exact


def test_exact_contours_meet_the_issue_targets(chain):
    _, s = chain
    assert s["r"]["jawOpen"] >= 0.9 and s["r"]["eyeBlink_L"] >= 0.9 and s["r"]["eyeBlink_R"] >= 0.9, s["r"]
    assert s["mean_r"] >= 0.8 and s["error_ratio"] <= 0.65, (s["mean_r"], s["error_ratio"])


def test_tracked_chain_regression_floor(chain):
    s, _ = chain
    assert s["mean_r"] >= 0.8 and s["r"]["jawOpen"] >= 0.85 and s["r"]["browInnerUp"] >= 0.9, s["r"]
    # a held expression taken for the actor's neutral loses that component (browOuterUp_L 0.28 with n/50)
    assert min(s["r"][c] for c in ("browOuterUp_L", "browOuterUp_R", "eyeBlink_L", "eyeBlink_R")) >= 0.85, s["r"]
    assert s["error_ratio"] < 0.75                         # closer to the truth than a still face (1.0)


@pytest.mark.xfail(strict=True, reason="issue 14 targets on tracked footage: rig vertex error 0.670 x > 0.65, "
                          "eyeBlink_L 0.895 < 0.9 (jawOpen 0.902, eyeBlink_R 0.921, mean r 0.819 are met)")
def test_tracked_chain_meets_the_issue_targets(chain):
    s, _ = chain
    assert s["r"]["jawOpen"] >= 0.9 and s["r"]["eyeBlink_L"] >= 0.9 and s["r"]["eyeBlink_R"] >= 0.9
    assert s["mean_r"] >= 0.8 and s["error_ratio"] <= 0.65
