"""Datasets: the neutral JSON layout format, ATISS preprocessed folders and the procedural generator."""

from __future__ import annotations

from pathlib import Path

from ..scene import Layout
from .atiss import is_atiss_folder, read_atiss_folder, write_atiss_folder
from .json_format import DatasetFormatError, read_json_layouts, write_json_layouts

PROCEDURAL_NAMES = ("procedural", "synthetic")


def load_layouts(source: str | Path, room_type: str | None = None, num_scenes: int = 1000,
                 seed: int = 0) -> list[Layout]:
    """Layouts from a JSON file, an ATISS folder, or ``"procedural"`` (the embedded generator)."""
    if str(source).lower() in PROCEDURAL_NAMES:
        from .procedural import generate_layouts

        if room_type is None:
            raise ValueError("the procedural generator needs a room type (bedroom, livingroom, diningroom)")
        return generate_layouts(room_type, num_scenes, seed=seed)
    path = Path(source)
    if path.is_dir():
        return read_atiss_folder(path, room_type)
    if path.suffix.lower() == ".json":
        return read_json_layouts(path, room_type)
    if not path.exists():
        raise FileNotFoundError(
            f"no such dataset: {path} (give a .json layout file, an ATISS folder or 'procedural')"
        )
    raise DatasetFormatError(f"{path}: not a .json layout file or an ATISS folder")


def save_layouts(layouts: list[Layout], dest: str | Path, **meta) -> Path:
    """Write layouts as neutral JSON (``*.json``) or as an ATISS folder (any other path)."""
    dest = Path(dest)
    if dest.suffix.lower() == ".json":
        return write_json_layouts(layouts, dest, meta or None)
    return write_atiss_folder(layouts, dest)


__all__ = ["DatasetFormatError", "is_atiss_folder", "load_layouts", "read_atiss_folder", "read_json_layouts",
           "save_layouts", "write_atiss_folder", "write_json_layouts"]
