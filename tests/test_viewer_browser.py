"""The 3D viewer in a real browser: headless Chromium (Debian's package) opens the page `iarcs data export` wrote
for bedrooms sampled from the shipped prior, draws the room, logs no error, and switches views and rooms.

The screenshot in docs/figures/viewer_bedroom.png is this test's, kept with
`IARCS_VIEWER_SHOT=docs/figures/viewer_bedroom.png .venv/bin/python -m pytest tests/test_viewer_browser.py`.
"""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
from PIL import Image

from browser import Browser, find_chromium
from experiments.cli import main
from iarcs_env.viewer import BUNDLE

CHROMIUM = find_chromium()
pytestmark = [
    pytest.mark.skipif(CHROMIUM is None, reason="no Chromium: `apt-get install chromium` (.ci/run does it)"),
    pytest.mark.skipif(not BUNDLE.is_file(), reason=f"the viewer is not built ({BUNDLE}): run `make viewer`"),
]
BACKGROUND = np.array([0xF4, 0xF4, 0xF2])


def drawn_fraction(shot, rect: dict) -> float:
    """The fraction of the canvas's pixels in a screenshot that are not the viewer's background."""
    image = np.asarray(Image.open(shot).convert("RGB"), dtype=np.int32)
    x0, y0 = int(rect["x"]), int(rect["y"])
    canvas = image[y0:y0 + int(rect["height"]), x0:x0 + int(rect["width"])]
    return float((np.abs(canvas - BACKGROUND).sum(-1) > 12).mean())


def test_the_viewer_draws_a_generated_bedroom_without_errors(tmp_path):
    rooms = tmp_path / "bedrooms.json"
    assert main(["sample", "--room", "bedroom", "--num-scenes", "3", "--seed", "4", "--out", str(rooms)]) == 0
    assert main(["data", "export", "--in", str(rooms), "--out", str(tmp_path / "export")]) == 0
    page = tmp_path / "export" / "viewer.html"
    with Browser(CHROMIUM) as browser:
        browser.open(page.as_uri())
        browser.wait_for("document.body.dataset.ready === '1'")
        rect = browser.evaluate("(() => { const r = document.querySelector('#view canvas').getBoundingClientRect();"
                                " return {x: r.x, y: r.y, width: r.width, height: r.height}; })()")
        assert rect["width"] > 400 and rect["height"] > 300
        orbit = browser.screenshot(tmp_path / "orbit.png")
        objects = int(browser.evaluate("document.body.dataset.objects"))
        legend = browser.evaluate("document.querySelectorAll('#legend li').length")
        browser.evaluate("document.getElementById('view-top').click()")
        top = browser.screenshot(tmp_path / "top.png")
        browser.evaluate("(() => { const s = document.getElementById('room'); s.value = '2';"
                         " s.dispatchEvent(new Event('change')); })()")
        browser.wait_for("document.body.dataset.ready === '1'")
        assert browser.evaluate("document.getElementById('room-info').textContent").startswith("bedroom")
        errors = browser.errors()
    assert errors == []
    first = json.loads(rooms.read_text())["scenes"][0]
    assert objects == len(first["objects"]) > 0
    assert 0 < legend <= objects
    assert drawn_fraction(orbit, rect) > 0.05  # the room, not a blank canvas
    assert drawn_fraction(top, rect) > 0.05
    assert not np.array_equal(np.asarray(Image.open(orbit)), np.asarray(Image.open(top)))
    if os.environ.get("IARCS_VIEWER_SHOT"):
        shutil.copy(orbit, os.environ["IARCS_VIEWER_SHOT"])
