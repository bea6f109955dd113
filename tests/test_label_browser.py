"""The correction page in a real browser: load, drag a point, save, step frames (headless Chromium)."""
from __future__ import annotations

import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from label_helpers import make_folder
from keyshape.base.formats.labels import read_pts
from keyshape.tracker.labelling.server import LabelServer

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture
def browser_page(tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed")
    if CHROMIUM is None:
        pytest.skip("Debian's chromium not installed (.ci/setup_browser.sh installs it)")
    with sync_api.sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True, args=ARGS,
            viewport={"width": 1000, "height": 800})
        try:
            yield ctx.new_page()
        finally:
            ctx.close()


@pytest.fixture
def server(tmp_path):
    srv = LabelServer(make_folder(tmp_path / "data", frames=(5, 40)), 0)
    t = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
    t.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def test_drag_save_and_step(browser_page, server):
    page = browser_page
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url)
    page.wait_for_selector("canvas[data-frame='000005']", timeout=15000)
    pts_path = server.folder / "000005.pts"
    before = read_pts(pts_path)
    other_before = read_pts(server.folder / "000040.pts")
    i = 30  # a lip point
    pos = page.evaluate(f"keyshapeLabel.screenPos({i})")
    scale = page.evaluate("keyshapeLabel.state.scale")
    dx, dy = 17.0, -9.0  # screen pixels
    page.mouse.move(pos["x"], pos["y"])
    page.mouse.down()
    page.mouse.move(pos["x"] + dx / 2, pos["y"] + dy / 2)
    page.mouse.move(pos["x"] + dx, pos["y"] + dy)
    page.mouse.up()
    assert "unsaved" in page.inner_text("#status")
    page.click("#save")
    page.wait_for_function("document.getElementById('status').textContent.startsWith('saved')", timeout=10000)
    after = read_pts(pts_path)
    expect = before.copy()
    expect[i] += [dx / scale, dy / scale]
    np.testing.assert_allclose(after, expect, atol=0.6 / scale + 2e-3)  # mouse events land on whole pixels
    assert np.linalg.norm(after[i] - before[i]) > 5 / scale
    # step to the next frame (button), then back with the keyboard: the saved drag is still there
    page.click("#next")
    page.wait_for_selector("canvas[data-frame='000040']", timeout=10000)
    np.testing.assert_allclose(read_pts(server.folder / "000040.pts"), other_before)  # untouched
    page.keyboard.press("ArrowLeft")
    page.wait_for_selector("canvas[data-frame='000005']", timeout=10000)
    shown = np.array(page.evaluate("keyshapeLabel.state.points"), dtype=float)
    np.testing.assert_allclose(shown, after, atol=1e-3)
    assert not errors, errors
