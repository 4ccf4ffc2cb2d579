"""Reader and writer for ATISS / ThreedFront preprocessed folders, so that data made here plugs into
ATISS, MiDiffusion and DiffuScene:

``ROOT/dataset_stats.txt`` (JSON: bounds and class lists) and one folder per room holding ``boxes.npz``
with ``class_labels`` (one-hot over the stats' ``class_labels``, which end in "start", "end"),
``translations`` (relative to ``floor_plan_centroid``), ``sizes`` (half extents), ``angles`` (L, 1),
``floor_plan_vertices`` / ``floor_plan_faces`` (triangle mesh, centred), ``floor_plan_centroid``, plus
MiDiffusion's ``floor_plan_ordered_corners`` and ``floor_plan_boundary_points_normals``.
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from ..floorplan import MAX_SIZE, FloorPlan, FloorPlanError
from ..rooms import get_room
from ..scene import Layout
from ..stats import ATISS_EXTRA_TOKENS, DatasetStats
from .json_format import DatasetFormatError, check_geometry

STATS_FILE = "dataset_stats.txt"
BOXES_FILE = "boxes.npz"


def is_atiss_folder(path: str | Path) -> bool:
    path = Path(path)
    return path.is_dir() and ((path / STATS_FILE).exists() or any(path.glob(f"*/{BOXES_FILE}")))


def _room_mask(floor: FloorPlan, size: int = 256, extent: float = 3.1) -> np.ndarray:
    """ATISS-style room mask: the floor (centred) seen from above over [-extent, extent]^2."""
    xs = (np.arange(size) + 0.5) / size * 2 * extent - extent
    gx, gz = np.meshgrid(xs, xs)
    return (floor.contains(gx, gz) * 255).astype(np.uint8)[..., None]


def write_atiss_folder(layouts: Sequence[Layout], root: str | Path, stats: DatasetStats | None = None) -> Path:
    """Write layouts as an ATISS preprocessed folder; ``stats`` default to the layouts' own."""
    if not layouts:
        raise ValueError("nothing to write: no layouts")
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    spec = get_room(layouts[0].room_type)
    stats = stats or DatasetStats.from_layouts(layouts, spec.name)
    stats.save(root / STATS_FILE)
    vocab = list(spec.classes) + list(ATISS_EXTRA_TOKENS)
    for i, lay in enumerate(layouts):
        if get_room(lay.room_type) != spec:
            raise ValueError(f"an ATISS folder holds one room type; scene {lay.id} is {lay.room_type}, not {spec.name}")
        centroid_xz = lay.floor.centre
        centroid = np.array([centroid_xz[0], 0.0, centroid_xz[1]])
        centred = lay.floor.translated(-centroid_xz)
        verts, faces = centred.triangulate()
        onehot = np.zeros((len(lay), len(vocab)), dtype=np.float32)
        for k, label in enumerate(lay.labels):
            onehot[k, vocab.index(label)] = 1
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", lay.id or "room")[-80:]
        folder = root / f"{i:05d}_{name}"
        folder.mkdir(exist_ok=True)
        np.savez_compressed(
            folder / BOXES_FILE,
            scene_id=np.array(lay.id), scene_type=np.array(spec.name),
            jids=np.array([str(e.get("jid", "")) for e in lay.extras]),
            uids=np.array([str(k) for k in range(len(lay))]),
            class_labels=onehot,
            translations=lay.translations - centroid,
            sizes=lay.half_sizes,
            angles=lay.yaws[:, None],
            floor_plan_vertices=verts, floor_plan_faces=faces, floor_plan_centroid=centroid,
            floor_plan_ordered_corners=centred.vertices,
            floor_plan_boundary_points_normals=centred.boundary_points(256),
            room_layout=_room_mask(centred),
            ceiling_height=np.array(lay.ceiling_height),
            extras_json=np.array(json.dumps([{k: v for k, v in e.items() if k != "jid"} for e in lay.extras])),
        )
    return root


def read_atiss_folder(root: str | Path, room_type: str | None = None) -> list[Layout]:
    """Read every ``*/boxes.npz`` under ``root`` (sorted by folder name) as layouts in absolute frame."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"no such ATISS folder: {root}")
    files = sorted(root.glob(f"*/{BOXES_FILE}"))
    if not files:
        raise DatasetFormatError(f"{root} holds no */{BOXES_FILE}: not an ATISS preprocessed folder")
    vocab = None
    if (root / STATS_FILE).exists():
        raw = json.loads((root / STATS_FILE).read_text())
        vocab = list(raw.get("class_labels", []))
        room_type = room_type or raw.get("room_type")
    layouts = []
    for f in files:
        try:
            layouts.append(_read_room(f, vocab, room_type))
        except KeyError as err:
            name = str(err.args[0]).split(" ")[0]
            raise DatasetFormatError(f"{f}: missing array '{name}' in boxes.npz") from None
        except (ValueError, FloorPlanError) as err:
            raise DatasetFormatError(f"{f}: {err}") from None
        except (OSError, EOFError, zipfile.BadZipFile) as err:  # truncated, empty or not an archive
            raise DatasetFormatError(f"{f}: not a readable .npz archive ({type(err).__name__}: {err})") from None
    return layouts


def _read_room(path: Path, vocab: list[str] | None, room_type: str | None) -> Layout:
    d = np.load(path, allow_pickle=False)
    room = room_type or (str(d["scene_type"]) if "scene_type" in d else None)
    if room is None:
        raise ValueError("no scene_type in boxes.npz and no dataset_stats.txt room_type; pass the room type")
    spec = get_room(_atiss_room_name(room))
    onehot = d["class_labels"]
    if vocab is None:
        vocab = list(spec.classes) + (list(ATISS_EXTRA_TOKENS) if onehot.shape[1] == len(spec.classes) + 2 else [])
    if onehot.shape[1] != len(vocab):
        raise ValueError(f"class_labels have {onehot.shape[1]} columns but the class list has {len(vocab)}")
    labels = [vocab[j] for j in onehot.argmax(1)]
    centroid = d["floor_plan_centroid"].astype(np.float64)
    if "floor_plan_ordered_corners" in d:
        floor = FloorPlan.from_vertices(d["floor_plan_ordered_corners"])
    else:
        floor = FloorPlan.from_triangles(d["floor_plan_vertices"], d["floor_plan_faces"])
    floor = floor.translated(centroid[[0, 2]])
    extras = json.loads(str(d["extras_json"])) if "extras_json" in d else [{} for _ in labels]
    jids = d["jids"] if "jids" in d else [""] * len(labels)
    for e, jid in zip(extras, jids):
        if str(jid):
            e["jid"] = str(jid)
    centres, halves = d["translations"].astype(np.float64) + centroid, d["sizes"].astype(np.float64)
    yaws = d["angles"].reshape(-1).astype(np.float64)
    if not len(centres) == len(halves) == len(yaws) == len(labels) or centres.shape[1:] != (3,) or halves.shape[1:] != (3,):
        raise ValueError(f"translations {centres.shape}, sizes {halves.shape}, angles {yaws.shape} and class_labels "
                         f"{onehot.shape} do not describe the same objects")
    for k in range(len(labels)):
        try:
            check_geometry(centres[k], halves[k], yaws[k])
        except ValueError as err:
            raise ValueError(f"object {k} ({labels[k]!r}): {err}") from None
    if "ceiling_height" in d and not 0 < float(d["ceiling_height"]) <= MAX_SIZE:
        raise ValueError(f"ceiling_height {float(d['ceiling_height'])} is not a height in metres in (0, {MAX_SIZE:g}]")
    return Layout(
        spec.name, floor, labels, centres, halves, yaws,
        id=str(d["scene_id"]) if "scene_id" in d else path.parent.name,
        ceiling_height=float(d["ceiling_height"]) if "ceiling_height" in d else 2.6, extras=extras,
    )


def _atiss_room_name(name: str) -> str:
    """ThreedFront scene types such as "MasterBedroom" or "LivingDiningRoom" onto our room names."""
    key = name.lower()
    if "bed" in key:
        return "bedroom"
    if "living" in key:
        return "livingroom"
    if "dining" in key:
        return "diningroom"
    return name
