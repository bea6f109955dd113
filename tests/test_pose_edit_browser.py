"""The pose-correction page in a real browser: load, move a slider, the pose is saved and re-rendered."""
from __future__ import annotations

import pytest

from keyshape.base.formats.poses import read_poses
from server_helpers import serving
from test_label_browser import browser_page  # noqa: F401 (fixture: headless Chromium, skipped where absent)
from test_pose_edit import pose_page_server
from test_rig_poses import SHAPES


@pytest.fixture
def server(tmp_path):
    with serving(pose_page_server(tmp_path)) as srv:
        yield srv


def test_slider_saves_the_pose_and_rerenders(browser_page, server):  # noqa: F811
    page = browser_page
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url)
    page.wait_for_selector("#sliders input[type=range]", timeout=15000)
    assert page.input_value("#key") == "mouth_0"
    assert page.eval_on_selector_all("#actor polygon, #actor polyline", "els => els.length") >= 2
    page.wait_for_function("document.getElementById('rig').naturalWidth === 96", timeout=10000)
    src0 = page.get_attribute("#rig", "src")
    # the jawOpen slider of mouth_0 (0.7 fitted) to 0.25, as a user's drag would end
    slider = page.locator("#sliders label", has_text="jawOpen").locator("xpath=following-sibling::input[1]")
    slider.evaluate("el => { el.value = 0.25; el.dispatchEvent(new Event('input')); }")
    page.wait_for_function("document.getElementById('status').textContent.startsWith('saved')", timeout=10000)
    pose = read_poses(server.path, list(SHAPES))["regions"]["mouth"]["keys"]["mouth_0"]
    assert pose["jawOpen"] == pytest.approx(0.25)
    page.wait_for_function(f"document.getElementById('rig').getAttribute('src') !== {src0!r}", timeout=10000)
    # another key: its own sliders (the eyes region's shapes)
    page.select_option("#key", "eyes_0")
    page.wait_for_selector("#sliders label:has-text('eyeBlink_L')", timeout=10000)
    assert not errors, errors
