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


def test_the_overlay_toggles_show_and_hide_the_flagged_objects(tmp_path):
    from iarcs_env.datasets import save_layouts
    from test_export3d import hand_room

    src = save_layouts([hand_room()], tmp_path / "room.json")  # collisions, one out of bound, one lifted
    assert main(["data", "export", "--in", str(src), "--out", str(tmp_path / "e")]) == 0
    with Browser(CHROMIUM) as browser:
        browser.open((tmp_path / "e" / "viewer.html").as_uri())
        browser.wait_for("document.body.dataset.ready === '1'")
        browser.evaluate("document.getElementById('view-top').click()")  # from above every outline shows
        counts = browser.evaluate("['colliding', 'out_of_bound', 'off_floor'].map("
                                  "f => document.getElementById('count-' + f).textContent)")
        on = browser.screenshot(tmp_path / "on.png")
        browser.evaluate("['show-colliding', 'show-out_of_bound', 'show-off_floor'].forEach(id => {"
                         " const box = document.getElementById(id); box.checked = false;"
                         " box.dispatchEvent(new Event('change')); })")
        off = browser.screenshot(tmp_path / "off.png")
        width = int(browser.evaluate("document.querySelector('#view canvas').getBoundingClientRect().width"))
        assert browser.errors() == []
    assert counts == ["(2)", "(1)", "(1)"]
    for rgb in ((230, 0, 0), (200, 0, 200), (0, 70, 255)):  # on the canvas, not the legend's swatches
        shown = np.asarray(Image.open(on))[:, :width]
        hidden = np.asarray(Image.open(off))[:, :width]
        assert overlay_pixels_array(shown, rgb) > 20 and overlay_pixels_array(hidden, rgb) == 0, rgb


def overlay_pixels_array(image: np.ndarray, rgb) -> int:
    return int((np.abs(image[..., :3].astype(np.int32) - np.asarray(rgb)).sum(-1) < 40).sum())
