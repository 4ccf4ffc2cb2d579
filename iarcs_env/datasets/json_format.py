"""Reader and writer for the neutral JSON layout format (``../shared/data/3dfront/README.md``):

``{"meta": {...}, "scenes": [{"id", "room_type", "floor": [[x, z], ...], "ceiling_height",
"objects": [{"label", "center": [x, y, z], "half_size": [hx, hy, hz], "yaw", ...}]}]}``
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

from ..floorplan import MAX_COORDINATE, MAX_SIZE, FloorPlan, FloorPlanError
from ..rooms import get_room
from ..scene import Layout

#: Object fields that the scene model owns; any other field (jid, coarse, ...) is kept as an extra.
_GEOMETRY_KEYS = ("label", "center", "half_size", "yaw")


class DatasetFormatError(ValueError):
    """A data file that cannot be read: the message names the file, the scene and the field."""


def _numbers(value, count: int, what: str) -> list[float]:
    """``value`` as ``count`` finite numbers (a JSON list of numbers, nothing else), or a ValueError saying why."""
    if not isinstance(value, (list, tuple)) or len(value) != count:
        raise ValueError(f"{what} must be a list of {count} numbers, got {json.dumps(value)[:60]}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise ValueError(f"{what} must hold numbers only, got {json.dumps(value)[:60]}")
    if not all(math.isfinite(v) for v in value):
        raise ValueError(f"{what} must be finite numbers, got {value}")
    return [float(v) for v in value]


def check_geometry(centre, half_size, yaw) -> None:
    """Refuse an object's numbers when not finite or beyond physical bounds (a ValueError naming the field)."""
    for name, values in (("center", centre), ("half_size", half_size), ("yaw", [yaw])):
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{name} must be finite numbers, got {[float(v) for v in values]}")
    if max(abs(v) for v in centre) > MAX_COORDINATE:
        raise ValueError(f"center {[float(v) for v in centre]} is more than {MAX_COORDINATE:g} m from the origin "
                         "(coordinates are metres)")
    if min(half_size) < 0 or 2 * max(half_size) > MAX_SIZE:
        raise ValueError(f"half_size {[float(v) for v in half_size]} must be >= 0 and at most {MAX_SIZE / 2:g} m "
                         f"(objects up to {MAX_SIZE:g} m)")
    if abs(yaw) > 100:
        raise ValueError(f"yaw {float(yaw)} is not an angle in radians")


def layout_from_json(scene: dict, where: str = "", room_type: str | None = None) -> Layout:
    """One scene dict of the neutral format as a :class:`Layout`."""
    sid = scene.get("id", "") if isinstance(scene, dict) else ""
    here = f"{where} scene {sid!r}" if sid else where
    if not isinstance(scene, dict):
        raise DatasetFormatError(f"{here}: a scene must be a JSON object, got {type(scene).__name__}")
    for key in ("floor", "objects"):
        if key not in scene:
            raise DatasetFormatError(f"{here}: missing field {key!r}")
    room = room_type or scene.get("room_type")
    if room is None:
        raise DatasetFormatError(f"{here}: missing field 'room_type' (bedroom, livingroom or diningroom)")
    try:
        spec = get_room(room)
        floor = FloorPlan.from_vertices(scene["floor"])
    except (ValueError, FloorPlanError) as err:
        raise DatasetFormatError(f"{here}: {err}") from None
    if not isinstance(scene["objects"], list):
        raise DatasetFormatError(f"{here}: 'objects' must be a list of objects, got {json.dumps(scene['objects'])[:60]}")
    height = scene.get("ceiling_height", 2.6)
    if not isinstance(height, (int, float)) or isinstance(height, bool) or not 0 < height <= MAX_SIZE:
        raise DatasetFormatError(f"{here}: ceiling_height must be a number of metres in (0, {MAX_SIZE:g}], got "
                                 f"{json.dumps(height)}")
    labels, centres, halves, yaws, extras = [], [], [], [], []
    for k, obj in enumerate(scene["objects"]):
        if not isinstance(obj, dict):
            raise DatasetFormatError(f"{here} object {k}: an object must be a JSON object, got {json.dumps(obj)[:60]}")
        missing = [f for f in _GEOMETRY_KEYS if f not in obj]
        if missing:
            raise DatasetFormatError(f"{here} object {k}: missing field(s) {', '.join(missing)}")
        try:
            spec.class_index(obj["label"])
            c = _numbers(obj["center"], 3, "center")
            h = _numbers(obj["half_size"], 3, "half_size")
            (y,) = _numbers([obj["yaw"]], 1, "yaw")
            check_geometry(c, h, y)
        except (TypeError, ValueError) as err:
            raise DatasetFormatError(f"{here} object {k} ({obj.get('label')!r}): {err}") from None
        labels.append(obj["label"])
        centres.append(c)
        halves.append(h)
        yaws.append(y)
        extras.append({key: v for key, v in obj.items() if key not in _GEOMETRY_KEYS})
    return Layout(spec.name, floor, labels, centres, halves, yaws, id=str(sid),
                  ceiling_height=float(height), extras=extras)


def layout_to_json(layout: Layout, digits: int = 6) -> dict:
    """A :class:`Layout` as one scene dict of the neutral format (numbers rounded to ``digits``)."""
    r = lambda v: round(float(v), digits)  # noqa: E731
    objects = []
    for k, label in enumerate(layout.labels):
        obj = {"label": label, "center": [r(v) for v in layout.translations[k]],
               "half_size": [r(v) for v in layout.half_sizes[k]], "yaw": r(layout.yaws[k])}
        obj.update(layout.extras[k] if k < len(layout.extras) else {})
        objects.append(obj)
    return {"id": layout.id, "room_type": layout.room_type,
            "floor": [[r(x), r(z)] for x, z in layout.floor.vertices],
            "ceiling_height": r(layout.ceiling_height), "objects": objects}


def read_json_layouts(path: str | Path, room_type: str | None = None) -> list[Layout]:
    """All scenes of a neutral-format JSON file, optionally only those of ``room_type``."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such layout file: {path}")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise DatasetFormatError(f"{path} is not valid JSON: {err}") from None
    if not isinstance(data, dict) or not isinstance(data.get("scenes"), list):
        raise DatasetFormatError(f"{path}: expected a JSON object with a \"scenes\" list (see the README's format)")
    want = get_room(room_type).name if room_type else None
    layouts = []
    for i, scene in enumerate(data["scenes"]):
        lay = layout_from_json(scene, where=f"{path} [scene {i}]")
        if want is None or lay.room_type == want:
            layouts.append(lay)
    return layouts


def write_json_layouts(layouts: Sequence[Layout], path: str | Path, meta: dict | None = None) -> Path:
    """Write layouts to a neutral-format JSON file (parent folders are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = sorted({get_room(l.room_type).name for l in layouts})
    head = {"source": "iarcs", "room_types": labels, "n_scenes": len(layouts)}
    head.update(meta or {})
    data = {"meta": head, "scenes": [layout_to_json(l) for l in layouts]}
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, separators=(",", ":")))
    tmp.replace(path)  # atomic: a crash never leaves half a file
    return path
