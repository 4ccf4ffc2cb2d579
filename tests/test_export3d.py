"""`iarcs data export`: rooms as glTF binary / OBJ read back with trimesh, 3D-FUTURE models fitted into their
boxes (a tiny model folder in 3D-FUTURE's layout, built here), and the viewer page's contents."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from shapely.geometry import Point, Polygon

from experiments.cli import main
from iarcs_env.datasets import save_layouts
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.floorplan import FloorPlan
from iarcs_env.scene import Layout
from iarcs_env.viewer import BUNDLE

L_FLOOR = [[0, 0], [5, 0], [5, 2], [2, 2], [2, 4], [0, 4]]  # non-convex, 14 m^2


def json_corners(obj: dict) -> np.ndarray:
    """The 8 corners of a neutral-JSON object, by the documented convention: a footprint corner (lx, lz)
    lands at (x + c lx + s lz, z - s lx + c lz)."""
    (x, y, z), (hx, hy, hz), yaw = obj["center"], obj["half_size"], obj["yaw"]
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[x + c * lx + s * lz, y + ly, z - s * lx + c * lz]
                     for lx in (-hx, hx) for ly in (-hy, hy) for lz in (-hz, hz)])


def same_points(a: np.ndarray, b: np.ndarray, tol: float = 1e-6) -> bool:
    """Every point of ``a`` has one of ``b`` within ``tol`` and back (order-free)."""
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return bool(len(a) and (d.min(1) <= tol).all() and (d.min(0) <= tol).all())


def hand_room() -> Layout:
    """An L-shaped bedroom: a bed, a nightstand overlapping it, a wardrobe through a wall, a lifted desk."""
    return Layout("bedroom", FloorPlan.from_vertices(L_FLOOR), ["double_bed", "nightstand", "wardrobe", "desk"],
                  translations=[[1.0, 0.4, 1.2], [1.85, 0.3, 0.5], [4.9, 1.0, 1.0], [0.6, 0.9, 3.5]],
                  half_sizes=[[0.8, 0.4, 1.0], [0.25, 0.3, 0.2], [0.3, 1.0, 0.6], [0.5, 0.38, 0.3]],
                  yaws=[0.3, 0.3, -np.pi / 2, np.pi], id="hand/L room", ceiling_height=2.7,
                  extras=[{"jid": "bed-jid"}, {}, {}, {}])


@pytest.fixture(scope="module")
def rooms_json(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rooms") / "rooms.json"
    save_layouts([hand_room()] + generate_layouts("bedroom", 5, seed=11) + generate_layouts("livingroom", 3, seed=2),
                 path)
    return path


def object_nodes(scene: trimesh.Scene) -> dict[str, tuple[np.ndarray, dict]]:
    """{node: (world vertices, extras)} of the objects in a glTF read back with trimesh."""
    found = {}
    for node in scene.graph.nodes_geometry:
        transform, geom = scene.graph[node]
        extras = scene.graph.transforms.edge_data[(scene.graph.transforms.parents[node], node)].get("metadata", {})
        if extras.get("kind") == "object":
            found[node] = (trimesh.transform_points(scene.geometry[geom].vertices, transform), extras)
    return found


def test_glb_export_reads_back_with_every_box_corner_and_the_floor_area(rooms_json, tmp_path):
    assert main(["data", "export", "--in", str(rooms_json), "--out", str(tmp_path)]) == 0
    scenes = json.loads(rooms_json.read_text())["scenes"]
    files = sorted(tmp_path.glob("*.glb"))
    assert len(files) == len(scenes) == 9
    for path, room in zip(files, scenes):
        scene = trimesh.load(path)
        objects = object_nodes(scene)
        assert len(objects) == len(room["objects"])
        for (vertices, extras), obj in zip(sorted(objects.values(), key=lambda v: v[1]["index"]), room["objects"]):
            assert extras["class"] == obj["label"] and extras["model"] == "box"
            assert same_points(vertices, json_corners(obj))  # within 1e-6 m
        transform, geom = scene.graph["floor"]
        floor = scene.geometry[geom]
        # glTF stores vertices as float32; the boxes' poses are node matrices (JSON numbers, float64)
        assert floor.area == pytest.approx(Polygon(room["floor"]).area, rel=1e-6)
        assert (floor.face_normals[:, 1] > 0.999).all()
        assert scene.metadata["room_type"] == room["room_type"] and scene.metadata["id"] == room["id"]


def test_a_non_convex_floor_is_triangulated_inside_its_polygon_and_walls_face_in(rooms_json, tmp_path):
    assert main(["data", "export", "--in", str(rooms_json), "--out", str(tmp_path), "--limit", "1"]) == 0
    scene = trimesh.load(next(tmp_path.glob("*.glb")))
    floor = scene.geometry[scene.graph["floor"][1]]
    polygon = Polygon(L_FLOOR)
    assert floor.area == pytest.approx(14.0)
    assert all(polygon.buffer(1e-9).contains(Point(c[0], c[2])) for c in floor.triangles_center)
    walls = scene.geometry[scene.graph["walls"][1]]
    assert len(walls.faces) == 2 * len(L_FLOOR) and walls.bounds[1, 1] == pytest.approx(2.7)
    # each wall's normal points into the room: a step along it from the wall's middle lands on the floor
    steps = walls.triangles_center[:, [0, 2]] + 0.05 * walls.face_normals[:, [0, 2]]
    assert all(polygon.contains(Point(*p)) for p in steps)


def test_object_metadata_holds_class_label_jid_and_the_plausibility_flags(rooms_json, tmp_path):
    assert main(["data", "export", "--in", str(rooms_json), "--out", str(tmp_path), "--limit", "1"]) == 0
    extras = {e["class"]: e for _, e in object_nodes(trimesh.load(next(tmp_path.glob("*.glb")))).values()}
    assert extras["double_bed"]["jid"] == "bed-jid" and "jid" not in extras["nightstand"]
    assert extras["nightstand"]["label"] == "nightstand 1"
    assert extras["double_bed"]["colliding"] and extras["nightstand"]["colliding"]
    assert not extras["wardrobe"]["colliding"] and extras["wardrobe"]["out_of_bound"]
    assert extras["desk"]["off_floor"] and not extras["desk"]["out_of_bound"] and not extras["desk"]["colliding"]
    assert not any(extras["double_bed"][k] for k in ("out_of_bound", "off_floor"))


def test_obj_export_reads_back_with_every_box_corner(rooms_json, tmp_path):
    assert main(["data", "export", "--in", str(rooms_json), "--out", str(tmp_path), "--format", "obj"]) == 0
    scenes = json.loads(rooms_json.read_text())["scenes"]
    files = sorted(tmp_path.glob("*.obj"))
    assert len(files) == len(scenes) and len(list(tmp_path.glob("*.mtl"))) == len(scenes)
    for path, room in zip(files, scenes):
        meshes = list(trimesh.load(path, split_object=True, group_material=False, process=False).geometry.values())
        assert len(meshes) == 2 + 2 * len(room["objects"])  # floor, walls, each box and its front bar
        for obj in room["objects"]:
            assert any(same_points(m.vertices, json_corners(obj)) for m in meshes), (path.name, obj["label"])
        floor = max(meshes, key=lambda m: (np.ptp(m.vertices[:, 1]) < 1e-12) * m.area)
        assert floor.area == pytest.approx(Polygon(room["floor"]).area, rel=1e-9)


# --- 3D-FUTURE ---------------------------------------------------------------------------------------------

def write_model(folder: Path, model_id: str, lo, hi) -> None:
    """A model folder as 3D-FUTURE lays it out: a box-shaped raw_model.obj spanning lo..hi, off-centre."""
    box = trimesh.creation.box(bounds=[lo, hi])
    (folder / model_id).mkdir(parents=True)
    (folder / model_id / "raw_model.obj").write_text(trimesh.exchange.obj.export_obj(box))


@pytest.fixture
def future_dir(tmp_path) -> Path:
    folder = tmp_path / "3D-FUTURE-model"
    write_model(folder, "ns-small", [0.1, 0, 0.1], [0.5, 0.5, 0.45])
    write_model(folder, "ns-tall", [-0.3, 0, -0.2], [0.3, 1.4, 0.2])
    write_model(folder, "bed-a", [-1, 0, -1.1], [1, 0.9, 1.1])
    write_model(folder, "bed-jid", [0, 0, 0], [1.6, 0.8, 2.0])
    info = [{"model_id": "ns-small", "category": "Nightstand", "super-category": "Cabinet/Shelf/Desk"},
            {"model_id": "ns-tall", "category": "Nightstand"},
            {"model_id": "bed-a", "category": "King-size Bed", "super-category": "Bed"},
            {"model_id": "bed-jid", "category": "Double Bed"},
            {"model_id": "lamp-missing", "category": "Pendant Lamp"}]  # listed, but its folder is absent
    (folder / "model_info.json").write_text(json.dumps(info))
    return folder


def local_bounds(vertices: np.ndarray, obj: dict) -> np.ndarray:
    """World vertices brought back into the object's own frame: their (min, max)."""
    c, s = np.cos(obj["yaw"]), np.sin(obj["yaw"])
    d = vertices - np.asarray(obj["center"])
    local = np.c_[c * d[:, 0] - s * d[:, 2], d[:, 1], s * d[:, 0] + c * d[:, 2]]
    return np.stack([local.min(0), local.max(0)])


def test_future_models_replace_boxes_by_jid_then_by_size(future_dir, tmp_path, capsys):
    room = hand_room()
    room.labels[2] = "pendant_lamp"  # its only model is missing: it stays a box
    src = save_layouts([room], tmp_path / "room.json")
    out = tmp_path / "export"
    assert main(["data", "export", "--in", str(src), "--out", str(out), "--future-dir", str(future_dir)]) == 0
    # the bed by its jid, the nightstand by size; no desk models, and the lamp's model folder is absent
    assert "2 box (no model of its class), 1 model by jid, 1 model by size" in capsys.readouterr().out
    objects = {e["class"]: (v, e) for v, e in object_nodes(trimesh.load(next(out.glob("*.glb")))).values()}
    room_json = json.loads(src.read_text())["scenes"][0]["objects"]
    assert objects["double_bed"][1]["model"] == "bed-jid"  # its own model
    assert objects["nightstand"][1]["model"] == "ns-small"  # 0.5 x 0.6 x 0.4 m: the small one, not the tall one
    assert objects["pendant_lamp"][1]["model"] == "box" and objects["desk"][1]["model"] == "box"
    for vertices, extras in objects.values():
        obj = room_json[extras["index"]]
        half = np.asarray(obj["half_size"])
        assert np.allclose(local_bounds(vertices, obj), [-half, half], atol=1e-6)  # scaled into its box


def test_future_models_pick_a_size_match_when_the_jid_is_not_in_the_folder(future_dir, tmp_path, capsys):
    room = hand_room()
    room.extras[0]["jid"] = "not-downloaded"
    src = save_layouts([room], tmp_path / "room.json")
    assert main(["data", "export", "--in", str(src), "--out", str(tmp_path / "e"), "--future-dir",
                 str(future_dir)]) == 0
    printed = capsys.readouterr().out
    assert "2 model by size" in printed and "2 box (no model of its class)" in printed
    extras = {e["class"]: e for _, e in object_nodes(trimesh.load(next((tmp_path / "e").glob("*.glb")))).values()}
    assert extras["double_bed"]["model"] in {"bed-a", "bed-jid"} and extras["double_bed"]["jid"] == "not-downloaded"


@pytest.mark.parametrize("damage, message", [
    (lambda d: (d / "model_info.json").unlink(), "has no model_info.json: --future-dir must be the 3D-FUTURE-model"),
    (lambda d: (d / "model_info.json").write_text("{not json"), "model_info.json is not valid JSON"),
    (lambda d: (d / "model_info.json").write_text('{"a": 1}'), "should hold a list of models, found dict"),
    (lambda d: (d / "model_info.json").write_text('[{"category": "Nightstand"}]'), "entry 0 has no model_id"),
])
def test_a_missing_or_malformed_future_folder_is_one_clear_line(future_dir, tmp_path, capsys, damage, message):
    damage(future_dir)
    src = save_layouts([hand_room()], tmp_path / "room.json")
    assert main(["data", "export", "--in", str(src), "--out", str(tmp_path / "x"), "--future-dir",
                 str(future_dir)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_a_damaged_model_file_costs_its_object_the_model_not_the_export(future_dir, tmp_path, capsys):
    (future_dir / "ns-small" / "raw_model.obj").write_text("v 0.1 0 0.1\nv 0.5 0.5 0.45\nf 1 2 9\n")
    (future_dir / "bed-jid" / "raw_model.obj").write_text("v 0 0 0\nv x y z\n")
    src = save_layouts([hand_room()], tmp_path / "room.json")
    assert main(["data", "export", "--in", str(src), "--out", str(tmp_path / "e"), "--future-dir",
                 str(future_dir)]) == 0
    assert "1 box (ns-small/raw_model.obj unreadable)" in capsys.readouterr().out
    extras = {e["class"]: e for _, e in object_nodes(trimesh.load(next((tmp_path / "e").glob("*.glb")))).values()}
    assert extras["nightstand"]["model"] == "box" and extras["double_bed"]["model"] == "bed-a"


# --- the viewer page ---------------------------------------------------------------------------------------

def test_the_viewer_page_embeds_every_exported_room_and_the_bundled_script(rooms_json, tmp_path):
    if not BUNDLE.is_file():
        pytest.skip(f"the viewer is not built ({BUNDLE}): run `make viewer` (needs node and npm)")
    assert main(["data", "export", "--in", str(rooms_json), "--out", str(tmp_path)]) == 0
    page = (tmp_path / "viewer.html").read_text()
    rooms = json.loads(page.split('id="iarcs-rooms">', 1)[1].split("</script>", 1)[0])
    assert len(rooms) == 9 and rooms[0]["meta"]["id"] == "hand/L room"
    import base64

    first = trimesh.load(trimesh.util.wrap_as_stream(base64.b64decode(rooms[0]["glb"])), file_type="glb")
    assert len(object_nodes(first)) == 4
    assert BUNDLE.read_text()[:2000] in page  # the script inline: nothing to fetch when the page opens
    assert "http://" not in page.split("<script>", 1)[0] and "https://" not in page.split("<script>", 1)[0]
