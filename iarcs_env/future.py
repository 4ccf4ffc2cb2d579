"""3D-FUTURE furniture models for exported rooms (``iarcs data export --future-dir PATH``).

The folder is the user's own download of 3D-FUTURE-model: ``model_info.json`` (a list of ``{"model_id",
"category", ...}``) and one folder per model holding ``raw_model.obj`` (with its ``model.mtl`` and
``texture.png``). An object is shown with the model its layout names (``jid``) when the folder has it,
else with the model of its class whose size is closest (the smallest summed |log| ratio of the three
extents, so a model is chosen for its proportions and scale alike), as ATISS and MiDiffusion retrieve
furniture. The model is centred and scaled per axis into the object's box. Objects whose class no model
covers stay boxes; :attr:`FutureModels.report` counts each outcome.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import trimesh

MODEL_FILE = "raw_model.obj"

#: 3D-FUTURE categories (lower case) -> the classes of the room types they furnish.
CATEGORY_CLASSES: dict[str, tuple[str, ...]] = {
    "armchair": ("armchair",),
    "bookcase / jewelry armoire": ("bookshelf",),
    "drawer chest / corner cabinet": ("cabinet",),
    "sideboard / side cabinet / console table": ("console_table", "cabinet"),
    "ceiling lamp": ("ceiling_lamp",),
    "pendant lamp": ("pendant_lamp",),
    "dining chair": ("dining_chair", "chair"),
    "lounge chair / cafe chair / office chair": ("lounge_chair", "chair"),
    "hanging chair": ("chair",),
    "dressing chair": ("dressing_chair",),
    "classic chinese chair": ("chinese_chair",),
    "children cabinet": ("children_cabinet",),
    "coffee table": ("coffee_table",),
    "corner/side table": ("corner_side_table", "table"),
    "round end table": ("round_end_table",),
    "dining table": ("dining_table", "table"),
    "desk": ("desk",),
    "dressing table": ("dressing_table",),
    "king-size bed": ("double_bed",),
    "double bed": ("double_bed",),
    "bed frame": ("double_bed",),
    "couch bed": ("double_bed",),
    "single bed": ("single_bed",),
    "bunk bed": ("single_bed",),
    "kids bed": ("kids_bed",),
    "nightstand": ("nightstand",),
    "shelf": ("shelf",),
    "tv stand": ("tv_stand",),
    "wardrobe": ("wardrobe",),
    "wine cabinet": ("wine_cabinet",),
    "three-seat / multi-seat sofa": ("multi_seat_sofa", "sofa"),
    "three-seat / multi-person sofa": ("multi_seat_sofa", "sofa"),
    "two-seat sofa": ("loveseat_sofa", "sofa"),
    "loveseat sofa": ("loveseat_sofa", "sofa"),
    "l-shaped sofa": ("l_shaped_sofa", "sofa"),
    "lazy sofa": ("lazy_sofa",),
    "chaise longue sofa": ("chaise_longue_sofa",),
    "barstool": ("stool",),
    "footstool / sofastool / bed end stool / stool": ("stool",),
}


class FutureError(ValueError):
    """The 3D-FUTURE folder is missing or not in 3D-FUTURE's layout (a user error, shown in one line)."""


def obj_extent(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The (min, max) corners of an OBJ file's vertices, read without building the mesh."""
    rows = [line.split()[1:4] for line in path.read_text(errors="replace").splitlines() if line.startswith("v ")]
    if not rows:
        raise FutureError(f"{path} has no vertices")
    v = np.asarray(rows, dtype=np.float64)
    return v.min(0), v.max(0)


class FutureModels:
    """A 3D-FUTURE-model folder: which models it has, by class, and each model fitted into a box."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        info_path = self.folder / "model_info.json"
        if not self.folder.is_dir():
            raise FutureError(f"--future-dir {self.folder} is not a folder: give the 3D-FUTURE-model folder "
                              "(the one holding model_info.json and a folder per model)")
        if not info_path.is_file():
            raise FutureError(f"{self.folder} has no model_info.json: --future-dir must be the 3D-FUTURE-model "
                              "folder (the one holding model_info.json and a folder per model)")
        try:
            info = json.loads(info_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise FutureError(f"{info_path} is not valid JSON ({e}); re-extract 3D-FUTURE-model") from None
        if not isinstance(info, list):
            raise FutureError(f"{info_path} should hold a list of models, found {type(info).__name__}")
        self.by_class: dict[str, list[str]] = {}
        for k, entry in enumerate(info):
            if not isinstance(entry, dict) or not isinstance(entry.get("model_id"), str):
                raise FutureError(f"{info_path}: entry {k} has no model_id string ({str(entry)[:80]})")
            category = str(entry.get("category") or "").strip().lower()
            for cls in CATEGORY_CLASSES.get(category, ()):
                self.by_class.setdefault(cls, []).append(entry["model_id"])
        self._extents: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
        self.report: Counter[str] = Counter()

    def _model_path(self, model_id: str) -> Path:
        return self.folder / model_id / MODEL_FILE

    def extent(self, model_id: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The model's bounding box (min, max), or None when its OBJ is missing, empty or flat."""
        if model_id not in self._extents:
            path = self._model_path(model_id)
            box = None
            if path.is_file():
                try:
                    lo, hi = obj_extent(path)
                    box = (lo, hi) if np.all(hi - lo > 1e-6) else None
                except (FutureError, ValueError):
                    box = None
            self._extents[model_id] = box
        return self._extents[model_id]

    def closest(self, cls: str, half_sizes: np.ndarray) -> str | None:
        """The model of class ``cls`` whose extents are closest to the box's (summed |log| ratio)."""
        target = np.log(2 * np.maximum(np.asarray(half_sizes, dtype=np.float64), 1e-6))
        best, best_cost = None, np.inf
        for model_id in self.by_class.get(cls, []):
            box = self.extent(model_id)
            if box is None:
                continue
            cost = float(np.abs(np.log(box[1] - box[0]) - target).sum())
            if cost < best_cost:
                best, best_cost = model_id, cost
        return best

    def fit(self, cls: str, half_sizes: np.ndarray, jid: str = "") -> tuple[str | None, trimesh.Trimesh | None]:
        """``(model_id, mesh)`` for an object: its own model (``jid``) when present, else the closest of its
        class, centred and scaled into the box ``half_sizes``; ``(None, None)`` when there is none."""
        model_id, how = (jid, "by jid") if jid and self.extent(jid) is not None else (None, "")
        if model_id is None:
            model_id, how = self.closest(cls, half_sizes), "by size"
        if model_id is None:
            self.report["box (no model of its class)"] += 1
            return None, None
        try:
            loaded = trimesh.load(self._model_path(model_id), force="mesh", process=False)
        except Exception:  # noqa: BLE001 - a damaged model file costs the object its model, not the export
            self.report[f"box ({model_id}/{MODEL_FILE} unreadable)"] += 1
            return None, None
        lo, hi = self.extent(model_id)
        scale = 2 * np.asarray(half_sizes, dtype=np.float64) / (hi - lo)
        loaded.apply_transform(np.diag([*scale, 1.0]) @ trimesh.transformations.translation_matrix(-(lo + hi) / 2))
        self.report[f"model {how}"] += 1
        return model_id, loaded
