"""Rooms as 3D scenes (glTF binary or OBJ), for Blender, three.js, Habitat or Isaac Sim, and for the viewer.

One :class:`~iarcs_env.scene.Layout` becomes a :class:`trimesh.Scene` in the layout's own metric frame (y up,
no recentring, so a file lines up with its JSON):

* ``floor``: the floor polygon triangulated at y = 0 (non-convex floors included), normals up;
* ``walls``: the polygon's boundary raised to the ceiling height, one quad per edge, two-sided;
* one node per object, ``NN_class``: a class-coloured box of the object's half sizes (or, with a
  :class:`~iarcs_env.future.FutureModels` library, its 3D-FUTURE model scaled into that box), posed by the
  object's yaw (R_y, ATISS convention) and centre; boxes get a dark bar along the top of their front face
  (local +z) as the child node ``NN_class_front``.

Each object node's glTF ``extras`` (three.js ``userData``) hold ``kind: "object"``, ``index``, ``class``,
``label`` (the class and its number in the room, "nightstand 2"), ``jid`` when the layout has one, ``model``
(the 3D-FUTURE model used, or ``"box"``), and the physical-plausibility flags of
:mod:`iarcs_env.metrics`: ``colliding``, ``out_of_bound``, ``off_floor``. The scene's extras hold the room's
id, type, ceiling height and floor polygon.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import trimesh
from trimesh.visual.material import PBRMaterial

from .render import PALETTE
from .scene import Layout

if TYPE_CHECKING:
    from .future import FutureModels
    from .metrics import SceneResult

FLOOR_RGBA = (176, 164, 146, 255)
WALL_RGBA = (240, 240, 236, 255)
FRONT_RGBA = (40, 40, 40, 255)
#: The front bar's thickness (m), and its length as a fraction of the box's width.
FRONT_BAR = 0.03
FRONT_BAR_WIDTH = 0.6


def object_pose(translation: np.ndarray, yaw: float) -> np.ndarray:
    """The 4x4 transform of an object: R_y(yaw) = [[c, 0, s], [0, 1, 0], [-s, 0, c]], then the centre."""
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    pose[:3, 3] = translation
    return pose


def _coloured(mesh: trimesh.Trimesh, rgba, name: str, double_sided: bool = False) -> trimesh.Trimesh:
    colour = np.asarray(rgba, dtype=np.float64) / 255.0
    mesh.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(
        name=name, baseColorFactor=colour, metallicFactor=0.0, roughnessFactor=0.9, doubleSided=double_sided))
    return mesh


def floor_mesh(layout: Layout) -> trimesh.Trimesh:
    """The floor polygon, triangulated (constrained Delaunay) at y = 0 with its faces' normals up (+y)."""
    vertices, faces = layout.floor.triangulate()
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    up = mesh.face_normals[:, 1] < 0
    mesh.faces[up] = mesh.faces[up][:, ::-1]
    return _coloured(mesh, FLOOR_RGBA, "floor")


def wall_mesh(layout: Layout) -> trimesh.Trimesh:
    """Zero-thickness walls: each edge of the floor polygon raised from y = 0 to the ceiling height, facing in."""
    v = layout.floor.vertices
    nxt = np.roll(v, -1, axis=0)
    h = layout.ceiling_height
    quads = np.stack([np.c_[v[:, 0], np.zeros(len(v)), v[:, 1]], np.c_[nxt[:, 0], np.zeros(len(v)), nxt[:, 1]],
                      np.c_[nxt[:, 0], np.full(len(v), h), nxt[:, 1]], np.c_[v[:, 0], np.full(len(v), h), v[:, 1]]],
                     axis=1)
    vertices = quads.reshape(-1, 3)
    base = 4 * np.arange(len(v))[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    # Face normals point into the room (the viewer draws only front faces: the near walls do not hide it).
    counter_clockwise = np.sum(v[:, 0] * nxt[:, 1] - nxt[:, 0] * v[:, 1]) > 0
    if not counter_clockwise:
        faces = faces[:, ::-1]
    return _coloured(trimesh.Trimesh(vertices, faces, process=False), WALL_RGBA, "wall", double_sided=True)


def box_mesh(half_sizes: np.ndarray, rgba, name: str) -> trimesh.Trimesh:
    """An axis-aligned box of the given half sizes about the origin, in the object's own frame."""
    return _coloured(trimesh.creation.box(extents=2 * np.asarray(half_sizes, dtype=np.float64)), rgba, name)


def front_bar(half_sizes: np.ndarray) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A dark bar inside the top edge of the box's front face (local +z), and its transform in the box."""
    hx, hy, hz = np.asarray(half_sizes, dtype=np.float64)
    t = min(FRONT_BAR, hy, hz)
    bar = box_mesh([FRONT_BAR_WIDTH * hx, t / 2, t / 2], FRONT_RGBA, "front")
    where = np.eye(4)
    where[:3, 3] = [0.0, hy - t / 2, hz - t / 2]
    return bar, where


def class_rgba(name: str) -> tuple[int, int, int, int]:
    return (*PALETTE.get(name, (128, 128, 128)), 255)


def layout_scene(layout: Layout, flags: "SceneResult | None" = None,
                 models: "FutureModels | None" = None) -> trimesh.Scene:
    """The room as a trimesh scene (see the module docstring); ``flags`` from
    :func:`iarcs_env.metrics.evaluate_layouts` with ``keep_scenes``, ``models`` a 3D-FUTURE library."""
    scene = trimesh.Scene()
    scene.metadata.update(id=layout.id, room_type=layout.room_type, ceiling_height=float(layout.ceiling_height),
                          floor=layout.floor.vertices.tolist())
    scene.add_geometry(floor_mesh(layout), node_name="floor", geom_name="floor", metadata={"kind": "floor"})
    scene.add_geometry(wall_mesh(layout), node_name="walls", geom_name="walls", metadata={"kind": "walls"})
    flagged = {key: set(getattr(flags, key)) if flags is not None else set()
               for key in ("colliding", "out_of_bound", "off_floor")}
    seen: Counter[str] = Counter()
    for i, cls in enumerate(layout.labels):
        seen[cls] += 1
        name = f"{i:02d}_{cls}"
        half = layout.half_sizes[i]
        jid = str(layout.extras[i].get("jid", "") or "")
        model_id, mesh = models.fit(cls, half, jid) if models is not None else (None, None)
        if mesh is None:
            mesh = box_mesh(half, class_rgba(cls), cls)
        info = {"kind": "object", "index": i, "class": cls, "label": f"{cls.replace('_', ' ')} {seen[cls]}",
                "model": model_id or "box", **{key: i in ids for key, ids in flagged.items()}}
        if jid:
            info["jid"] = jid
        scene.add_geometry(mesh, node_name=name, geom_name=name,
                           transform=object_pose(layout.translations[i], float(layout.yaws[i])), metadata=info)
        if model_id is None:
            bar, where = front_bar(half)
            scene.add_geometry(bar, node_name=f"{name}_front", geom_name=f"{name}_front", parent_node_name=name,
                               transform=where, metadata={"kind": "front", "index": i})
    return scene


def file_stem(index: int, layout: Layout) -> str:
    """``00003_<room id>``, the id reduced to characters safe in any file system (at most 60)."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", layout.id).strip("._")[-60:]
    return f"{index:05d}_{safe}" if safe else f"{index:05d}"


def glb_bytes(scene: trimesh.Scene) -> bytes:
    return scene.export(file_type="glb")


def write_scene(scene: trimesh.Scene, path: Path, fmt: str) -> Path:
    """Write ``scene`` as ``path`` with suffix ``.glb``, or ``.obj`` with its ``.mtl`` beside it."""
    if fmt == "glb":
        path = path.with_suffix(".glb")
        path.write_bytes(glb_bytes(scene))
        return path
    path = path.with_suffix(".obj")
    obj, mtl = obj_text(scene, path.with_suffix(".mtl").name)
    path.write_text(obj)
    path.with_suffix(".mtl").write_text(mtl)
    return path


def obj_text(scene: trimesh.Scene, mtl_name: str) -> tuple[str, str]:
    """The scene as OBJ text, one ``o`` group per node in world coordinates (mm precision to 1e-8 m), and its
    MTL text (flat colours; textures only travel in glTF)."""
    lines, materials, offset = [f"mtllib {mtl_name}"], {}, 1
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        mesh = scene.geometry[geom_name]
        material = getattr(mesh.visual, "material", None)
        colour = getattr(material, "baseColorFactor", None)
        name = getattr(material, "name", None) or "default"
        materials[name] = np.asarray(colour if colour is not None else [180, 180, 180, 255], dtype=np.float64)
        vertices = trimesh.transform_points(mesh.vertices, transform)
        lines += [f"o {node}", f"usemtl {name}"]
        lines += [f"v {x:.8f} {y:.8f} {z:.8f}" for x, y, z in vertices]
        lines += [f"f {a} {b} {c}" for a, b, c in mesh.faces + offset]
        offset += len(vertices)
    mtl = []
    for name, rgba in materials.items():
        rgb = rgba[:3] / 255.0 if rgba.max() > 1 else rgba[:3]
        mtl += [f"newmtl {name}", "Kd {:.4f} {:.4f} {:.4f}".format(*rgb), ""]
    return "\n".join(lines) + "\n", "\n".join(mtl)


def scene_flags(layouts: Sequence[Layout]) -> list["SceneResult"]:
    """The per-scene plausibility flags of :mod:`iarcs_env.metrics`, in order, for layouts of any room types."""
    from .metrics import evaluate_layouts

    flags: list = [None] * len(layouts)
    for room in dict.fromkeys(lay.room_type for lay in layouts):
        idx = [i for i, lay in enumerate(layouts) if lay.room_type == room]
        scenes = evaluate_layouts([layouts[i] for i in idx], keep_scenes=True)["scenes"]
        for i, result in zip(idx, scenes):
            flags[i] = result
    return flags
