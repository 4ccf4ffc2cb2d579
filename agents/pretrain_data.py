"""The pretraining data pipeline: a dataset's rooms as metric tensors (:class:`SceneTensors`), their
training / validation split and feature statistics, and the augmentation (90-degree rotations, slot
permutations) done on the tensors."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
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

    @classmethod
    def from_layouts(cls, layouts: Sequence[Layout], num_slots: int, num_points: int = 256) -> "SceneTensors":
        b = SceneBatch.from_layouts(layouts, num_slots=num_slots)
        pts = torch.tensor(np.stack([f.boundary_points(num_points) for f in b.floors]), dtype=torch.float32)
        return cls(b.labels, b.translations, b.half_sizes, b.yaws, pts, floor_half_extents(b.floors))

    def __len__(self) -> int:
        return self.labels.shape[0]

    def to(self, device) -> "SceneTensors":
        """The same tensors on ``device`` (the training device: batches are then drawn and augmented there)."""
        return SceneTensors(*(getattr(self, f.name).to(device) for f in fields(self)))

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
            trans[..., [0, 2]] = rotate_xz_tensor(trans[..., [0, 2]], c[:, None], s[:, None])
            pts[..., 0:2] = rotate_xz_tensor(pts[..., 0:2], c[:, None], s[:, None])
            pts[..., 2:4] = rotate_xz_tensor(pts[..., 2:4], c[:, None], s[:, None])
            yaws = yaws + ang[:, None]
            yaws = (yaws + math.pi) % (2 * math.pi) - math.pi
            extents = torch.where((k % 2 == 1)[:, None], extents.flip(-1), extents)  # 90 degrees swap x, z
        if permute:
            perm = torch.rand(b, n, generator=generator, device=labels.device).argsort(1)
            labels = labels.gather(1, perm)
            trans = trans.gather(1, perm[..., None].expand(-1, -1, 3))
            half = half.gather(1, perm[..., None].expand(-1, -1, 3))
            yaws = yaws.gather(1, perm)
        return labels, trans, half, yaws, pts, extents


def rotate_xz_tensor(p: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """(x, z) -> (c x + s z, -s x + c z): the R_y of :func:`iarcs_env.floorplan.rotate_xz`."""
    x, z = p[..., 0], p[..., 1]
    return torch.stack([c * x + s * z, -s * x + c * z], -1)


def encode_batch(spec, stats: DatasetStats, labels, trans, half, yaws, pts, extents):
    """(x0 features (B, N, 8+K), floor features (B, P, 4)) of metric tensors (see :meth:`SceneTensors.batch`)."""
    x0 = SceneBatch(spec, labels, trans, half, yaws, floors=[]).encode(stats, extents)
    return x0, scale_floor_points(pts, stats)



def stats_for_training(layouts: Sequence[Layout], room: str, rotation_augment: bool) -> DatasetStats:
    """Dataset statistics; with rotation augmentation the translation bounds cover all four rotations."""
    stats = DatasetStats.from_layouts(layouts, room)
    if rotation_augment:
        rotated = [lay.centred().rotated(k * math.pi / 2) for lay in layouts for k in (1, 2, 3)]
        wide = DatasetStats.from_layouts(list(layouts) + rotated, room)
        stats.bounds_translations = wide.bounds_translations
    return stats


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
    order = np.random.default_rng(cfg.data_seed).permutation(len(layouts))
    n_val = min(cfg.val_scenes, len(layouts) // 10)
    return [layouts[i] for i in order[n_val:]], [layouts[i] for i in order[:n_val]]


