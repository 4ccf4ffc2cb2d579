"""Dataset statistics in ATISS's ``dataset_stats.txt`` JSON layout: feature bounds, class lists and
frequencies, furniture counts, plus the object-count histogram used by the object-count prior."""

from __future__ import annotations

import functools
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .rooms import EMPTY, get_room

#: ATISS appends these tokens to the class list in dataset_stats.txt and the boxes.npz one-hots.
ATISS_EXTRA_TOKENS = ("start", "end")
#: How model features scale the floor-plane translations: by each room's floor half-extent, or by the
#: dataset bounds (see :class:`DatasetStats`).
TRANSLATION_FRAMES = ("room", "dataset")


@functools.lru_cache(maxsize=64)
def _constant(values: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``values`` as a tensor, made once per device and dtype: a GPU training step copies nothing from the host
    (never modify the result in place)."""
    return torch.tensor(values, dtype=dtype, device=device)


@dataclass
class DatasetStats:
    """Bounds and frequencies of one room type's training data.

    ``bounds_translations`` and ``bounds_sizes`` are ``[min_x, min_y, min_z, max_x, max_y, max_z]``;
    ``bounds_angles`` is ``[min, max]``; ``object_count_histogram[k]`` counts rooms with k objects;
    ``class_presence[c]`` is the fraction of rooms with at least one object of class c;
    ``class_sizes[c]`` is ``{"log_mean": [x, y, z], "log_std": [x, y, z]}``, the mean and standard deviation
    of the logarithm of class c's half-sizes (classes with at least two objects; the ``object_size``
    reward).

    ``translation_frame`` says how the model features scale the floor-plane translations (x, z):
    ``"room"`` divides each object's centre by its free half-range in its room, the floor's bounding-box
    half-extent minus the footprint's own half-extent along that axis, so that +-1 is an object touching
    a wall of a rectangular room whatever the sizes of room and object (:func:`iarcs_env.scene.translation_scale`); ``"dataset"``
    (ATISS / MiDiffusion, and every statistics file written before this field existed) scales them with
    ``bounds_translations`` like the height. The height (y) always uses ``bounds_translations``.
    """

    room_type: str
    bounds_translations: list[float]
    bounds_sizes: list[float]
    bounds_angles: list[float] = field(default_factory=lambda: [-np.pi, np.pi])
    class_frequencies: dict[str, float] = field(default_factory=dict)
    count_furniture: dict[str, int] = field(default_factory=dict)
    object_count_histogram: list[int] = field(default_factory=list)
    class_presence: dict[str, float] = field(default_factory=dict)
    translation_frame: str = "room"
    class_sizes: dict[str, dict[str, list[float]]] = field(default_factory=dict)

    def __post_init__(self):
        if self.translation_frame not in TRANSLATION_FRAMES:
            raise ValueError(f"translation_frame must be one of {', '.join(TRANSLATION_FRAMES)}; "
                             f"got {self.translation_frame!r}")

    @property
    def spec(self):
        return get_room(self.room_type)

    @property
    def class_labels(self) -> list[str]:
        return list(self.spec.classes)

    def translation_bounds(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = _constant(tuple(self.bounds_translations), like.dtype, like.device)
        return b[:3], b[3:]

    def size_bounds(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = _constant(tuple(self.bounds_sizes), like.dtype, like.device)
        return b[:3], b[3:]

    def count_distribution(self, num_slots: int | None = None) -> np.ndarray:
        """Normalised object-count histogram over 0..num_slots."""
        n = num_slots if num_slots is not None else self.spec.max_objects
        h = np.zeros(n + 1)
        for k, c in enumerate(self.object_count_histogram[: n + 1]):
            h[k] = c
        return h / max(h.sum(), 1)

    # --- construction -----------------------------------------------------------------------------------
    @classmethod
    def from_layouts(cls, layouts: Sequence, room_type: str | None = None, margin: float = 0.0) -> "DatasetStats":
        """Compute statistics from layouts (translations taken relative to each floor's centre)."""
        if not layouts:
            raise ValueError("cannot compute dataset statistics from no layouts")
        spec = get_room(room_type or layouts[0].room_type)
        trans, sizes, counts, labels, present = [], [], [], [], Counter()
        for lay in layouts:
            c = lay.centred()
            trans.append(c.translations)
            sizes.append(c.half_sizes)
            counts.append(len(c))
            labels.extend(c.labels)
            present.update(set(c.labels))
        t = np.concatenate(trans) if labels else np.zeros((1, 3))
        s = np.concatenate(sizes) if labels else np.full((1, 3), 0.5)
        t_lo, t_hi = t.min(0) - margin, t.max(0) + margin
        s_lo, s_hi = s.min(0), s.max(0) + margin
        counter = Counter(labels)
        total = max(sum(counter.values()), 1)
        hist = np.bincount(counts, minlength=spec.max_objects + 1)
        return cls(
            room_type=spec.name,
            bounds_translations=[float(v) for v in np.concatenate([t_lo, t_hi])],
            bounds_sizes=[float(v) for v in np.concatenate([s_lo, s_hi])],
            class_frequencies={c: counter.get(c, 0) / total for c in spec.classes},
            count_furniture={c: int(counter.get(c, 0)) for c in spec.classes},
            object_count_histogram=[int(v) for v in hist],
            class_presence={c: present.get(c, 0) / len(layouts) for c in spec.classes},
            class_sizes=_class_sizes(np.array(labels), s),
        )

    # --- dataset_stats.txt ------------------------------------------------------------------------------
    def to_json(self) -> dict:
        freq_order = sorted(self.class_frequencies, key=lambda c: -self.class_frequencies[c])
        return {
            "bounds_translations": self.bounds_translations,
            "bounds_sizes": self.bounds_sizes,
            "bounds_angles": self.bounds_angles,
            "class_labels": self.class_labels + list(ATISS_EXTRA_TOKENS),
            "object_types": self.class_labels,
            "class_frequencies": self.class_frequencies,
            "class_order": {c: i for i, c in enumerate(freq_order)},
            "count_furniture": sorted(self.count_furniture.items(), key=lambda kv: -kv[1]),
            "room_type": self.room_type,
            "object_count_histogram": self.object_count_histogram,
            "class_presence": self.class_presence,
            "translation_frame": self.translation_frame,
            "class_sizes": self.class_sizes,
        }

    @classmethod
    def from_json(cls, data: dict, room_type: str | None = None) -> "DatasetStats":
        missing = [k for k in ("bounds_translations", "bounds_sizes") if k not in data]
        if missing:
            raise ValueError(f"dataset statistics lack {', '.join(missing)}")
        room = room_type or data.get("room_type") or _guess_room(data.get("class_labels", []))
        count = data.get("count_furniture", {})
        if isinstance(count, list):  # ATISS writes a list of [label, count] pairs
            count = {k: v for k, v in count}
        return cls(
            room_type=get_room(room).name,
            bounds_translations=[float(v) for v in data["bounds_translations"]],
            bounds_sizes=[float(v) for v in data["bounds_sizes"]],
            bounds_angles=[float(v) for v in data.get("bounds_angles", [-np.pi, np.pi])],
            class_frequencies={k: float(v) for k, v in data.get("class_frequencies", {}).items()},
            count_furniture={k: int(v) for k, v in count.items()},
            object_count_histogram=[int(v) for v in data.get("object_count_histogram", [])],
            class_presence={k: float(v) for k, v in data.get("class_presence", {}).items()},
            translation_frame=data.get("translation_frame", "dataset"),  # files from before the field
            class_sizes={k: {m: [float(x) for x in v[m]] for m in ("log_mean", "log_std")}
                         for k, v in data.get("class_sizes", {}).items()},
        )

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1))

    @classmethod
    def load(cls, path: str | Path, room_type: str | None = None) -> "DatasetStats":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise FileNotFoundError(f"no dataset statistics at {path}") from None
        except json.JSONDecodeError as err:
            raise ValueError(f"{path} is not JSON dataset statistics ({err})") from None
        return cls.from_json(data, room_type)


def _class_sizes(labels: np.ndarray, half_sizes: np.ndarray) -> dict[str, dict[str, list[float]]]:
    """Mean and standard deviation of log half-sizes for each class with at least two objects."""
    out = {}
    for c in sorted(set(labels.tolist())):
        logs = np.log(np.maximum(half_sizes[labels == c], 1e-4))
        if len(logs) >= 2:
            out[c] = {"log_mean": [float(v) for v in logs.mean(0)], "log_std": [float(v) for v in logs.std(0)]}
    return out


def _guess_room(class_labels: Sequence[str]) -> str:
    labels = {c for c in class_labels if c not in ATISS_EXTRA_TOKENS and c != EMPTY}
    if "double_bed" in labels or "nightstand" in labels:
        return "bedroom"
    if labels:
        return "livingroom"
    raise ValueError("dataset statistics name no room type and no class labels; add \"room_type\"")
