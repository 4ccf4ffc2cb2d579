"""The pretraining data pipeline: a dataset's rooms as metric tensors (:class:`SceneTensors`), optionally in a
canonical slot order, their training / validation split and feature statistics, and the augmentation (90-degree
rotations, slot permutations) done on the tensors."""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np
import torch

from iarcs_env.rooms import get_room
from iarcs_env.scene import Layout, SceneBatch, floor_half_extents, scale_floor_points
from iarcs_env.stats import DatasetStats

if TYPE_CHECKING:
    from .pretrain import PretrainConfig

REPO_ROOT = Path(__file__).resolve().parents[1]

def resolve_dataset(source: str) -> str:
    """``procedural`` as is; a relative path from the working directory, else from the repository root."""
    if source.lower() in ("procedural", "synthetic"):
        return source
    p = Path(source).expanduser()
    if p.is_absolute():
        candidates = [p]
    else:
        candidates = [Path.cwd() / p, REPO_ROOT / p]
    for c in candidates:
        if c.exists():
            return str(c.resolve())
    raise FileNotFoundError(
        f"dataset {source!r} not found (looked at {', '.join(str(c) for c in candidates)}); give a path to a "
        "neutral-JSON layout file or an ATISS folder, or 'procedural'")



@dataclass
class SceneTensors:
    """A dataset as metric tensors in the scene frame (floors centred), ready for augmentation."""

    labels: torch.Tensor  # (S, N)
    translations: torch.Tensor  # (S, N, 3)
    half_sizes: torch.Tensor  # (S, N, 3)
    yaws: torch.Tensor  # (S, N)
    floor_points: torch.Tensor  # (S, P, 4): x, z, nx, nz in metres
    extents: torch.Tensor  # (S, 2): the floors' half-extents (x, z) in metres
    draw_weights: torch.Tensor | None = None  # (S,): each room's chance in a batch (None: all alike)

    @classmethod
    def from_layouts(cls, layouts: Sequence[Layout], num_slots: int, num_points: int = 256,
                     canonical_order: bool = False) -> "SceneTensors":
        """The rooms' tensors, their objects in the rooms' order or, with ``canonical_order``, sorted by class
        index (a stable sort: objects of one class keep the room's order), empty slots (the largest index)
        last: the one place where the canonical order of ``PretrainConfig.canonical_order`` is made."""
        b = SceneBatch.from_layouts(layouts, num_slots=num_slots)
        slots = (b.labels, b.translations, b.half_sizes, b.yaws)
        if canonical_order:
            slots = gather_slots(b.labels.argsort(dim=1, stable=True), *slots)
        pts = torch.tensor(np.stack([f.boundary_points(num_points) for f in b.floors]), dtype=torch.float32)
        return cls(*slots, pts, floor_half_extents(b.floors))

    def __len__(self) -> int:
        return self.labels.shape[0]

    def to(self, device) -> "SceneTensors":
        """The same tensors on ``device`` (the training device: batches are then drawn and augmented there)."""
        values = (getattr(self, f.name) for f in fields(self))
        return SceneTensors(*(None if v is None else v.to(device) for v in values))

    @staticmethod
    def room_fields() -> list[str]:
        """The per-room tensors: all but ``draw_weights``, which only a mix of datasets has."""
        return [f.name for f in fields(SceneTensors) if f.name != "draw_weights"]

    @staticmethod
    def mixed(parts: Sequence[tuple["SceneTensors", float]]) -> "SceneTensors":
        """The rooms of ``parts`` together, a batch drawing from each part its weight's share of the rooms
        (uniformly within a part)."""
        names = SceneTensors.room_fields()
        weights = torch.cat([torch.full((len(part),), weight / len(part)) for part, weight in parts])
        return SceneTensors(*(torch.cat([getattr(part, n) for part, _ in parts]) for n in names),
                            weights / weights.sum())

    def batch(self, idx: torch.Tensor, generator: torch.Generator | None = None, rotate: bool = False,
              permute: bool = False):
        """Metric tensors of scenes ``idx``, optionally rotated by random multiples of 90 degrees about +y
        and with shuffled slots. Returns (labels, translations, half_sizes, yaws, floor_points, extents)."""
        labels, trans = self.labels[idx], self.translations[idx].clone()
        half, yaws, pts = self.half_sizes[idx], self.yaws[idx].clone(), self.floor_points[idx].clone()
        extents = self.extents[idx].clone()
        b, n = labels.shape
        if rotate:
            k = torch.randint(0, 4, (b,), generator=generator, device=labels.device)
            ang = k.float() * (math.pi / 2)
            c, s = torch.cos(ang).round(), torch.sin(ang).round()  # exact for multiples of 90 degrees
            trans[..., 0::2] = rotate_xz_tensor(trans[..., 0::2], c[:, None], s[:, None])  # x, z (a slice, not a
            # list index: that would copy the index to the GPU and wait)
            pts[..., 0:2] = rotate_xz_tensor(pts[..., 0:2], c[:, None], s[:, None])
            pts[..., 2:4] = rotate_xz_tensor(pts[..., 2:4], c[:, None], s[:, None])
            yaws = yaws + ang[:, None]
            yaws = (yaws + math.pi) % (2 * math.pi) - math.pi
            extents = torch.where((k % 2 == 1)[:, None], extents.flip(-1), extents)  # 90 degrees swap x, z
        if permute:
            perm = torch.rand(b, n, generator=generator, device=labels.device).argsort(1)
            labels, trans, half, yaws = gather_slots(perm, labels, trans, half, yaws)
        return labels, trans, half, yaws, pts, extents


def gather_slots(order: torch.Tensor, labels, trans, half, yaws):
    """The slots of each scene reordered: slot i of scene b gets what its slot ``order[b, i]`` held."""
    return (labels.gather(1, order), trans.gather(1, order[..., None].expand(-1, -1, 3)),
            half.gather(1, order[..., None].expand(-1, -1, 3)), yaws.gather(1, order))


def rotate_xz_tensor(p: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """(x, z) -> (c x + s z, -s x + c z): the R_y of :func:`iarcs_env.floorplan.rotate_xz`."""
    x, z = p[..., 0], p[..., 1]
    return torch.stack([c * x + s * z, -s * x + c * z], -1)


def encode_batch(spec, stats: DatasetStats, labels, trans, half, yaws, pts, extents):
    """(x0 features (B, N, 8+K), floor features (B, P, 4)) of metric tensors (see :meth:`SceneTensors.batch`)."""
    x0 = SceneBatch(spec, labels, trans, half, yaws, floors=[]).encode(stats, extents)
    return x0, scale_floor_points(pts, stats)



def stats_for_training(layouts: Sequence[Layout], room: str, rotation_augment: bool,
                       rotated: np.ndarray | None = None) -> DatasetStats:
    """Dataset statistics; with rotation augmentation the translation bounds cover all four rotations
    (``rotated``: the rooms' :func:`rotated_translation_bounds`, when they are at hand)."""
    stats = DatasetStats.from_layouts(layouts, room)
    if rotation_augment:
        r = rotated_translation_bounds(layouts) if rotated is None else rotated
        # the bounds of the rooms and their rotated copies together (the plain bounds are 0 with no objects)
        lo = np.minimum(np.array(stats.bounds_translations[:3]), r[:, :3].min(0, initial=np.inf))
        hi = np.maximum(np.array(stats.bounds_translations[3:]), r[:, 3:].max(0, initial=-np.inf))
        stats.bounds_translations = [float(v) for v in np.concatenate([lo, hi])]
    return stats


def rotated_translation_bounds(layouts: Sequence[Layout]) -> np.ndarray:
    """(S, 6): per room, the least and greatest (x, y, z) of its objects' centres in its copies rotated by 90,
    180 and 270 degrees (each centred on its floor as :meth:`DatasetStats.from_layouts` centres a room);
    +inf and -inf for a room without objects. Per room, so that chunks of rooms can be done apart."""
    out = np.empty((len(layouts), 6))
    out[:, :3], out[:, 3:] = np.inf, -np.inf
    for i, lay in enumerate(layouts):
        if len(lay):
            c = lay.centred()
            t = np.concatenate([c.rotated(k * math.pi / 2).centred().translations for k in (1, 2, 3)])
            out[i, :3], out[i, 3:] = t.min(0), t.max(0)
    return out


def load_training_layouts(cfg: "PretrainConfig", log: Callable[[str], None] = print) -> list[Layout]:
    """The dataset of ``cfg``, without rooms that have more objects than the room type has slots."""
    from iarcs_env.datasets import load_layouts

    spec = get_room(cfg.room)
    source = resolve_dataset(cfg.dataset)
    layouts = load_layouts(source, spec.name, num_scenes=cfg.num_scenes, seed=cfg.data_seed)
    layouts = [l for l in layouts if get_room(l.room_type).name == spec.name]
    kept = [l for l in layouts if len(l) <= spec.max_objects]
    if len(kept) < len(layouts):
        log(f"dropped {len(layouts) - len(kept)} of {len(layouts)} rooms with more than {spec.max_objects} objects")
    if not kept:
        raise ValueError(f"{cfg.dataset}: no {spec.name} rooms with at most {spec.max_objects} objects")
    return kept



def training_split(layouts: Sequence[Layout], cfg: "PretrainConfig") -> tuple[list[Layout], list[Layout]]:
    """(training, validation) rooms: a permutation of ``data_seed`` holds out ``val_scenes`` (at most a tenth),
    after dropping rooms with more objects than the room type has slots."""
    spec = get_room(cfg.room)
    layouts = [l for l in layouts if len(l) <= spec.max_objects]
    train_idx, val_idx = split_indices(len(layouts), cfg)
    return [layouts[i] for i in train_idx], [layouts[i] for i in val_idx]


def split_indices(num_rooms: int, cfg: "PretrainConfig") -> tuple[np.ndarray, np.ndarray]:
    """(training, validation) indices of :func:`training_split` among ``num_rooms`` kept rooms."""
    order = np.random.default_rng(cfg.data_seed).permutation(num_rooms)
    n_val = min(cfg.val_scenes, num_rooms // 10)
    return order[n_val:], order[:n_val]


# --------------------------------------------------------------------------------------------------------
# The data of a run: computed, or for procedural rooms read from a cache
# --------------------------------------------------------------------------------------------------------
#: Boundary points per floor in the training tensors.
FLOOR_POINTS = 256
#: Version of what the cache holds and how it is computed: bump it whenever the tensors or statistics of
#: :func:`training_data` change for the same rooms (:meth:`SceneTensors.from_layouts`, :func:`stats_for_training`,
#: :func:`training_split`); the procedural rooms themselves are versioned by ``GENERATOR_VERSION``.
CACHE_VERSION = 1
#: The cache's root folder (default ``out/cache``, from the working directory); the pretraining data lie in
#: its ``pretrain_data`` folder.
CACHE_ENV = "IARCS_CACHE_DIR"
_CACHE_FORMAT = "iarcs pretraining data"
#: Rooms per worker process at least: fewer rooms are generated in fewer processes (a small dataset in this one).
ROOMS_PER_PROCESS = 500


def training_data(cfg: "PretrainConfig", layouts: Sequence[Layout] | None = None,
                  log: Callable[[str], None] = print, progress: bool = True,
                  with_stats: bool = True) -> tuple[SceneTensors, SceneTensors | None, DatasetStats | None]:
    """(training rooms, validation rooms or None, statistics of the training rooms) of ``cfg``'s dataset, or of
    ``layouts`` when given. Procedural rooms (``dataset: procedural``) come from a cache file keyed by
    :func:`cache_key` (:func:`cache_path`), made on the first run by generating the rooms in one process per
    core; other datasets are computed. ``with_stats=False`` skips the statistics where they would be computed
    (a resumed run has its own; None then)."""
    from iarcs_env.datasets import PROCEDURAL_NAMES

    spec = get_room(cfg.room)
    if layouts is None and resolve_dataset(cfg.dataset).lower() in PROCEDURAL_NAMES:
        data, val, stats = procedural_training_data(cfg, log, progress)
    else:
        if layouts is None:
            layouts = load_training_layouts(cfg, log)
        train_layouts, val_layouts = training_split(layouts, cfg)
        stats = stats_for_training(train_layouts, spec.name, cfg.rotation_augment) if with_stats else None
        data = SceneTensors.from_layouts(train_layouts, spec.max_objects, FLOOR_POINTS, cfg.canonical_order)
        val = SceneTensors.from_layouts(val_layouts, spec.max_objects, FLOOR_POINTS, cfg.canonical_order) \
            if val_layouts else None
    if cfg.extra_datasets:
        parts = [(data, 1.0)]
        for extra in cfg.extra_datasets:
            rooms = load_training_layouts(replace(cfg, dataset=extra["dataset"]), log)
            parts.append((SceneTensors.from_layouts(rooms, spec.max_objects, FLOOR_POINTS, cfg.canonical_order),
                          float(extra["weight"])))
            log(f"{len(rooms)} rooms of {extra['dataset']} at weight {extra['weight']:g} beside {len(data)} of "
                f"{cfg.dataset} (weight 1)")
        data = SceneTensors.mixed(parts)
    return data, val, stats


def cache_key(cfg: "PretrainConfig") -> dict:
    """What the cached pretraining data of ``cfg``'s procedural rooms depend on."""
    from iarcs_env.datasets.procedural import GENERATOR_VERSION

    spec = get_room(cfg.room)
    return {"room": spec.name, "num_scenes": int(cfg.num_scenes), "data_seed": int(cfg.data_seed),
            "val_scenes": int(cfg.val_scenes), "rotation_augment": bool(cfg.rotation_augment),
            "canonical_order": cfg.canonical_order, "num_slots": spec.max_objects,
            "num_points": FLOOR_POINTS, "generator_version": GENERATOR_VERSION, "cache_version": CACHE_VERSION}


def cache_dir() -> Path:
    """The folder of the cached pretraining data: ``$IARCS_CACHE_DIR/pretrain_data``, by default
    ``out/cache/pretrain_data`` under the working directory."""
    return Path(os.environ.get(CACHE_ENV) or "out/cache").expanduser() / "pretrain_data"


def cache_path(key: dict) -> Path:
    """The cache file of ``key`` (:func:`cache_key`): every part of the key is in its name."""
    name = (f"{key['room']}-n{key['num_scenes']}-seed{key['data_seed']}-val{key['val_scenes']}"
            f"-rot{int(key['rotation_augment'])}" + ("-canonical" if key["canonical_order"] else "")
            + f"-slots{key['num_slots']}-p{key['num_points']}-gen{key['generator_version']}"
            f"-v{key['cache_version']}.pt")
    return cache_dir() / name


def procedural_training_data(cfg: "PretrainConfig", log: Callable[[str], None] = print,
                             progress: bool = True) -> tuple[SceneTensors, SceneTensors | None, DatasetStats]:
    """:func:`training_data` of procedural rooms: read from the cache, or built and written to it. Under
    ``torchrun`` rank 0 builds and writes, the other ranks wait for it and read the file."""
    from . import distributed

    key = cache_key(cfg)
    path = cache_path(key)
    if distributed.world_size() > 1 and not distributed.is_main():
        written = distributed.broadcast_object(None)  # waits for rank 0's cache
        found = _read_cache(path, key, log) if written else None
        return found if found is not None else _build(cfg, log, progress=False)
    found = _read_cache(path, key, log)
    if found is None:
        found = _build(cfg, log, progress)
        written = _write_cache(path, key, *found, log)
    else:
        written = True
    if distributed.world_size() > 1:
        distributed.broadcast_object(written)
    return found


def _build(cfg: "PretrainConfig", log: Callable[[str], None], progress: bool):
    """The procedural rooms' tensors and statistics, generated in one process per core (for 500 rooms or more)."""
    from functools import partial

    from iarcs_env.datasets.procedural import available_cores, map_room_chunks

    spec = get_room(cfg.room)
    n = int(cfg.num_scenes)
    processes = max(1, min(available_cores(), n // ROOMS_PER_PROCESS))
    log(f"generating {n:,} procedural {spec.name}s in {processes} process{'es' if processes > 1 else ''}")
    t0 = time.perf_counter()
    work = partial(_chunk_data, num_slots=spec.max_objects, canonical_order=cfg.canonical_order,
                   rotation=cfg.rotation_augment)
    layouts, arrays, rotated, dropped = [], [], [], 0
    for rooms, tensors, rot, lost in map_room_chunks(spec.name, n, work, seed=cfg.data_seed, processes=processes,
                                                     progress=progress):
        layouts += rooms
        dropped += lost
        if rooms:
            arrays.append(tensors)
            rotated.append(rot)
    if dropped:
        log(f"dropped {dropped} of {n} rooms with more than {spec.max_objects} objects")
    if not layouts:
        raise ValueError(f"{cfg.dataset}: no {spec.name} rooms with at most {spec.max_objects} objects")
    names = SceneTensors.room_fields()
    stacked = {name: np.concatenate([a[name] for a in arrays]) for name in names}
    train_idx, val_idx = split_indices(len(layouts), cfg)
    rot = np.concatenate(rotated)[train_idx] if cfg.rotation_augment else None
    stats = stats_for_training([layouts[i] for i in train_idx], spec.name, cfg.rotation_augment, rot)
    data = SceneTensors(*(torch.from_numpy(stacked[name][train_idx]) for name in names))
    val = SceneTensors(*(torch.from_numpy(stacked[name][val_idx]) for name in names)) if len(val_idx) else None
    log(f"generated {len(layouts):,} rooms in {time.perf_counter() - t0:.1f} s")
    return data, val, stats


def _chunk_data(rooms: list[Layout], num_slots: int, canonical_order: bool, rotation: bool):
    """In a worker process: a chunk of rooms' tensors (as NumPy arrays) and rotated bounds, without the rooms
    with more objects than ``num_slots``; (rooms, arrays, bounds, number dropped)."""
    kept = [l for l in rooms if len(l) <= num_slots]
    if not kept:
        return [], None, None, len(rooms)
    t = SceneTensors.from_layouts(kept, num_slots, FLOOR_POINTS, canonical_order)
    arrays = {name: getattr(t, name).numpy() for name in t.room_fields()}
    return kept, arrays, rotated_translation_bounds(kept) if rotation else None, len(rooms) - len(kept)


def _pack(t: SceneTensors | None) -> dict | None:
    """Plain tensors of ``t`` for the file; the floor normals in float16 where that is exact, bit for bit (the
    axis-aligned walls' -1, 0, 1: a quarter less file)."""
    if t is None:
        return None
    out = {name: getattr(t, name) for name in t.room_fields()}
    normals = t.floor_points[..., 2:]
    if torch.equal(normals.half().float().view(torch.int32), normals.view(torch.int32)):
        out["floor_points"] = t.floor_points[..., :2].contiguous()
        out["floor_normals_half"] = normals.half()
    return out


def _unpack(d: dict) -> SceneTensors:
    d = dict(d)
    if "floor_normals_half" in d:
        d["floor_points"] = torch.cat([d["floor_points"], d.pop("floor_normals_half").float()], -1)
    t = SceneTensors(**{name: d.pop(name) for name in SceneTensors.room_fields()})
    if d:
        raise ValueError(f"unknown entries {sorted(d)}")
    rows = {name: getattr(t, name).shape[0] for name in t.room_fields()}
    if len(set(rows.values())) != 1:
        raise ValueError(f"tensors of different lengths {rows}")
    return t


def _write_cache(path: Path, key: dict, data: SceneTensors, val: SceneTensors | None, stats: DatasetStats,
                 log: Callable[[str], None]) -> bool:
    """Write the cache file atomically (a temporary file renamed); False, with a log line, when that fails."""
    from .denoiser import atomic_torch_save

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_torch_save({"format": _CACHE_FORMAT, "key": key, "train": _pack(data), "val": _pack(val),
                           "stats": json.dumps(stats.to_json())}, path)
    except OSError as err:
        log(f"could not write the data cache {path} ({err}); the next run generates the rooms again")
        return False
    log(f"cached at {path} ({path.stat().st_size / 1e6:.1f} MB)")
    return True


def _read_cache(path: Path, key: dict, log: Callable[[str], None]):
    """(data, val, stats) from the cache file, or None (no file; or an unreadable or foreign one, logged)."""
    if not path.exists():
        return None
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(saved, dict) or saved.get("format") != _CACHE_FORMAT:
            raise ValueError("not a pretraining data cache")
        if saved.get("key") != key:
            theirs = saved.get("key") if isinstance(saved.get("key"), dict) else {}
            differ = [f"{k}={theirs.get(k)!r}" for k in key if theirs.get(k) != key[k]]
            raise ValueError(f"it holds other data ({', '.join(differ) or 'another key'})")
        data = _unpack(saved["train"])
        val = _unpack(saved["val"]) if saved["val"] is not None else None
        stats = DatasetStats.from_json(json.loads(saved["stats"]), key["room"])
    except Exception as err:  # noqa: BLE001 - whatever is wrong with the file, the data are built again
        log(f"ignored the data cache {path}: {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}; "
            "building it again")
        return None
    log(f"read {len(data):,} training" + (f" and {len(val):,} validation" if val is not None else "")
        + f" rooms from cache {path}")
    return data, val, stats
