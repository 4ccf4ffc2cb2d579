import json

import numpy as np
import pytest

from iarcs_env.datasets import DatasetFormatError, load_layouts, read_atiss_folder, save_layouts
from iarcs_env.datasets.json_format import layout_to_json, read_json_layouts, write_json_layouts
from conftest import L_SHAPE, make_layout

OBJECTS = [
    ("double_bed", (2.0, 0.4, 1.0), (0.9, 0.4, 1.05), 1.5708),
    ("nightstand", (0.3, 0.25, 2.4), (0.25, 0.25, 0.2), -1.5708),
    ("pendant_lamp", (2.0, 2.3, 1.5), (0.3, 0.2, 0.3), 0.0),
]


def _layouts():
    a = make_layout(OBJECTS, id="a")
    a.extras[0]["jid"] = "model-123"
    a.extras[1]["coarse"] = "nightstand"
    b = make_layout(OBJECTS[1:], floor=tuple((x + 5.25, z - 1.5) for x, z in L_SHAPE), id="b:Bedroom-1")
    b.translations += [5.25, 0, -1.5]
    return [a, b]


def test_json_round_trip(tmp_path):
    path = write_json_layouts(_layouts(), tmp_path / "scenes.json")
    data = json.loads(path.read_text())
    assert data["meta"]["n_scenes"] == 2 and data["scenes"][0]["objects"][0]["jid"] == "model-123"
    back = read_json_layouts(path)
    assert [layout_to_json(l) for l in back] == [layout_to_json(l) for l in _layouts()]


def test_json_to_atiss_to_json_keeps_every_number(tmp_path):
    layouts = _layouts()
    write_json_layouts(layouts, tmp_path / "in.json")
    save_layouts(read_json_layouts(tmp_path / "in.json"), tmp_path / "atiss")
    back = load_layouts(tmp_path / "atiss")
    save_layouts(back, tmp_path / "out.json")
    a = json.loads((tmp_path / "in.json").read_text())["scenes"]
    b = json.loads((tmp_path / "out.json").read_text())["scenes"]
    assert a == b


def test_atiss_folder_follows_atiss_conventions(tmp_path):
    save_layouts(_layouts(), tmp_path / "atiss")
    stats = json.loads((tmp_path / "atiss" / "dataset_stats.txt").read_text())
    assert stats["class_labels"][-2:] == ["start", "end"] and len(stats["class_labels"]) == 23
    assert len(stats["bounds_translations"]) == 6 and len(stats["bounds_sizes"]) == 6
    rooms = sorted((tmp_path / "atiss").glob("*/boxes.npz"))
    assert len(rooms) == 2
    d = np.load(rooms[1])
    assert d["class_labels"].shape == (2, 23) and d["angles"].shape == (2, 1)
    # translations relative to the floor's bounding-box centre, floor mesh centred too
    np.testing.assert_allclose(d["floor_plan_centroid"], [7.25, 0, 0.5])
    np.testing.assert_allclose(d["translations"][0], [0.3 + 5.25 - 7.25, 0.25, 2.4 - 1.5 - 0.5])
    verts = d["floor_plan_vertices"]
    assert verts.shape[1] == 3 and np.allclose(verts.min(0), [-2, 0, -2]) and np.allclose(verts.max(0), [2, 0, 2])
    assert d["floor_plan_boundary_points_normals"].shape == (256, 4)


def test_atiss_reader_accepts_mesh_only_floors(tmp_path):
    save_layouts(_layouts(), tmp_path / "atiss")
    for f in (tmp_path / "atiss").glob("*/boxes.npz"):
        d = dict(np.load(f))
        del d["floor_plan_ordered_corners"], d["extras_json"], d["ceiling_height"]
        np.savez(f, **d)
    back = read_atiss_folder(tmp_path / "atiss")
    assert back[1].floor.polygon.symmetric_difference(_layouts()[1].floor.polygon).area < 1e-9
    np.testing.assert_allclose(back[1].translations, _layouts()[1].translations, atol=1e-12)


def test_real_bedrooms_load(real_bedrooms_path):
    layouts = load_layouts(real_bedrooms_path)
    assert len(layouts) == 500 and sum(len(l) for l in layouts) == 2335
    assert all(l.room_type == "bedroom" for l in layouts)


def _write(tmp_path, scenes, raw=None):
    path = tmp_path / "bad.json"
    path.write_text(raw if raw is not None else json.dumps({"scenes": scenes}))
    return path


GOOD_OBJECT = {"label": "nightstand", "center": [1, 0.25, 1], "half_size": [0.2, 0.25, 0.2], "yaw": 0}
GOOD_SCENE = {"id": "s", "room_type": "bedroom", "floor": [[0, 0], [3, 0], [3, 3], [0, 3]], "objects": [GOOD_OBJECT]}


#: Scenes that are not data, and what the error says (also fed to every command: tests/test_cli_inputs.py).
BAD_SCENES = [
    ({**GOOD_SCENE, "floor": [[0, 0], [1, 1]]}, "at least 3"),
    ({**GOOD_SCENE, "floor": [[0, 0], [1, 1], [1, 0], [0, 1]]}, "not simple"),
    ({k: v for k, v in GOOD_SCENE.items() if k != "objects"}, "missing field 'objects'"),
    ({k: v for k, v in GOOD_SCENE.items() if k != "room_type"}, "room_type"),
    ({**GOOD_SCENE, "room_type": "garage"}, "unknown room type"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "label": "piano"}]}, "unknown bedroom class 'piano'"),
    ({**GOOD_SCENE, "objects": [{k: v for k, v in GOOD_OBJECT.items() if k != "yaw"}]}, "missing field.*yaw"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "half_size": [0.2, -1, 0.2]}]}, "half_size .* must be >= 0"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "center": [1, 2]}]}, "3 numbers"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "yaw": "north"}]}, "yaw must hold numbers only"),
    # numbers that are not data (issue 42): each refused, naming the scene, the object and the field
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "center": "123"}]}, r"object 0 \('nightstand'\): center must be a list"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "center": [float("nan"), 0, 1]}]}, "center must be finite"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "center": [float("inf"), 0, 1]}]}, "center must be finite"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "center": [1e300, 0, 1]}]}, "more than 1000 m from the origin"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "half_size": [0.2, 1e300, 0.2]}]}, "at most 25 m"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "half_size": [0.2, float("nan"), 0.2]}]}, "half_size must be finite"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "yaw": float("nan")}]}, "yaw must be finite"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "yaw": 1e9}]}, "not an angle in radians"),
    ({**GOOD_SCENE, "objects": [{**GOOD_OBJECT, "center": [True, 0, 1]}]}, "numbers only"),
    ({**GOOD_SCENE, "objects": 5}, "'objects' must be a list"),
    ({**GOOD_SCENE, "objects": [5]}, "object 0: an object must be a JSON object"),
    ({**GOOD_SCENE, "ceiling_height": None}, "ceiling_height must be a number"),
    ({**GOOD_SCENE, "ceiling_height": -2.6}, "ceiling_height must be a number"),
    ({**GOOD_SCENE, "floor": [[0, 0], [1e200, 0], [0, 3]]}, "vertex 1 .* more than 1000 m"),
    ({**GOOD_SCENE, "floor": [[0, 0], [float("nan"), 0], [0, 3]]}, "vertex 1 is not a finite number"),
]


@pytest.mark.parametrize("scene, message", BAD_SCENES)
def test_malformed_json_scenes_raise_clear_errors(tmp_path, scene, message):
    with pytest.raises(DatasetFormatError, match=message) as err:
        read_json_layouts(_write(tmp_path, [scene]))
    assert "bad.json" in str(err.value)


def test_malformed_json_files(tmp_path):
    with pytest.raises(DatasetFormatError, match="not valid JSON"):
        read_json_layouts(_write(tmp_path, None, raw="{oops"))
    with pytest.raises(DatasetFormatError, match="\"scenes\" list"):
        read_json_layouts(_write(tmp_path, None, raw="[1, 2]"))
    with pytest.raises(FileNotFoundError, match="no such layout file"):
        read_json_layouts(tmp_path / "missing.json")
    with pytest.raises(FileNotFoundError, match="no such dataset"):
        load_layouts(tmp_path / "missing.txt")


def test_malformed_atiss_folders(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetFormatError, match="not an ATISS"):
        read_atiss_folder(tmp_path / "empty")
    save_layouts(_layouts(), tmp_path / "atiss")
    f = sorted((tmp_path / "atiss").glob("*/boxes.npz"))[0]
    d = dict(np.load(f))
    good = d["class_labels"]
    d["class_labels"] = good[:, :5]
    np.savez(f, **d)
    with pytest.raises(DatasetFormatError, match="class_labels have 5 columns"):
        read_atiss_folder(tmp_path / "atiss")
    d["class_labels"] = good
    del d["translations"]
    np.savez(f, **d)
    with pytest.raises(DatasetFormatError, match="missing array 'translations'"):
        read_atiss_folder(tmp_path / "atiss")


@pytest.mark.parametrize("damage, message", [
    (lambda f, d: f.write_bytes(f.read_bytes()[:200]), "not a readable .npz archive"),  # truncated
    (lambda f, d: f.write_bytes(b""), "not a readable .npz archive"),  # empty
    (lambda f, d: np.savez(f, **{**d, "translations": d["translations"] * np.nan}), r"object 0 .*center must be finite"),
    (lambda f, d: np.savez(f, **{**d, "sizes": d["sizes"] * 1e300}), r"half_size .* at most 25 m"),
    (lambda f, d: np.savez(f, **{**d, "angles": d["angles"] + np.inf}), "yaw must be finite"),
    (lambda f, d: np.savez(f, **{**d, "translations": d["translations"][:1]}), "do not describe the same objects"),
    (lambda f, d: np.savez(f, **{**d, "ceiling_height": np.float64(-1)}), "ceiling_height -1.0 is not a height"),
])
def test_damaged_atiss_archives_are_one_clear_error(tmp_path, damage, message):
    save_layouts(_layouts(), tmp_path / "atiss")
    f = sorted((tmp_path / "atiss").glob("*/boxes.npz"))[0]
    damage(f, dict(np.load(f)))
    with pytest.raises(DatasetFormatError, match=message) as err:
        read_atiss_folder(tmp_path / "atiss")
    assert str(f) in str(err.value)
