"""The 3D viewer: one static HTML page showing exported rooms (orbit and top views, a class legend, the
overlays of the PNG renders as toggles), written next to exports and reports.

The page is self-contained: the rooms are embedded as glTF binaries and the script is ``data/viewer.js``,
three.js and ``viewer/src/viewer.js`` bundled by ``make viewer`` from pinned npm packages (``viewer/``), so
nothing is fetched when the page is opened, from a file or a server alike.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Sequence

import trimesh

from .scene3d import glb_bytes

BUNDLE = Path(__file__).parent / "data" / "viewer.js"
#: At most this many rooms go into one page (a page holds every room it shows).
VIEWER_ROOMS = 50


class ViewerNotBuilt(RuntimeError):
    """The viewer's script bundle is missing: build it with ``make viewer`` (needs node and npm)."""


def bundle() -> str:
    if not BUNDLE.is_file():
        raise ViewerNotBuilt(f"the 3D viewer is not built ({BUNDLE} is missing): run `make viewer` (needs node "
                             "and npm) or `make install`, which builds it")
    return BUNDLE.read_text()


_PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>
  html, body {{ margin: 0; height: 100%; font: 14px/1.4 system-ui, sans-serif; color: #222; }}
  body {{ display: flex; }}
  #view {{ flex: 1; min-width: 0; }}
  #panel {{ width: 250px; padding: 12px 14px; box-sizing: border-box; overflow-y: auto; border-left: 1px solid #ddd;
           background: #fafafa; }}
  h1 {{ font-size: 15px; margin: 0 0 8px; }}
  h2 {{ font-size: 13px; margin: 14px 0 4px; color: #555; }}
  select {{ width: 100%; }}
  button {{ padding: 3px 10px; border: 1px solid #aaa; background: #fff; border-radius: 3px; cursor: pointer; }}
  button.active {{ background: #333; color: #fff; }}
  label {{ display: block; }}
  ul {{ list-style: none; padding: 0; margin: 0; }}
  .swatch {{ display: inline-block; width: 12px; height: 12px; margin-right: 6px; vertical-align: -1px;
             border: 1px solid #0003; }}
  .small {{ font-size: 12px; color: #555; }}
</style>
</head>
<body>
<div id="view"></div>
<div id="panel">
  <h1>{title}</h1>
  <select id="room" aria-label="room"></select>
  <p class="small" id="room-info"></p>
  <h2>View</h2>
  <button id="view-orbit" class="active">Orbit</button> <button id="view-top">Top</button>
  <p class="small">Drag to turn, scroll to zoom, right-drag to pan.</p>
  <h2>Show</h2>
  <label><input type="checkbox" id="show-walls" checked> walls</label>
  <label><input type="checkbox" id="show-colliding" checked>
    <span class="swatch" style="background:#e60000"></span>collisions <span id="count-colliding"></span></label>
  <label><input type="checkbox" id="show-out_of_bound" checked>
    <span class="swatch" style="background:#c800c8"></span>out of bound <span id="count-out_of_bound"></span></label>
  <label><input type="checkbox" id="show-off_floor" checked>
    <span class="swatch" style="background:#0046ff"></span>off the floor <span id="count-off_floor"></span></label>
  <h2>Classes</h2>
  <ul id="legend"></ul>
  <p class="small" id="picked"></p>
</div>
<script type="application/json" id="iarcs-rooms">{rooms}</script>
<script>{script}</script>
</body>
</html>
"""


def write_viewer(scenes: Sequence[tuple[str, trimesh.Scene]], path: str | Path, title: str = "iarcs rooms") -> Path:
    """Write the viewer page for ``(name, scene)`` pairs (scenes from :func:`iarcs_env.scene3d.layout_scene`)."""
    script = bundle()
    rooms = [{"name": name, "meta": {k: scene.metadata.get(k) for k in ("id", "room_type", "ceiling_height")},
              "glb": base64.b64encode(glb_bytes(scene)).decode("ascii")} for name, scene in scenes]
    # "</" would end the script element early; JSON allows the escaped form.
    payload = json.dumps(rooms).replace("</", "<\\/")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(_PAGE.format(title=html.escape(title), rooms=payload, script=script.replace("</script", "<\\/script")))
    return path
