"""Top-down renders: class-coloured oriented boxes on the floor plan, seen from above.

The image's x axis is the scene's +x, its rows run along +z. Ground objects are drawn lowest first, so a
taller object covers a lower one as a camera above the room would see it; ceiling and pendant lamps are
drawn as outlines only. A short dark tick marks each object's front (local +z). Optional overlays mark
colliding objects (red), out-of-bound objects (magenta), objects off the floor (sunk or lifted; blue diagonals)
and unreachable free floor (orange), as used by
evaluation reports and by reward reflection.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from .rooms import BEDROOM_CLASSES, CEILING_CLASSES, LIVING_DINING_CLASSES
from .scene import Layout, box_corners_xz

# A fixed palette: the same class has the same colour in every room type and every run.
_PALETTE_HEX = [
    "#1f77b4", "#aec7e8", "#ff7f0e", "#ffbb78", "#2ca02c", "#98df8a", "#d62728", "#ff9896", "#9467bd",
    "#c5b0d5", "#8c564b", "#c49c94", "#e377c2", "#f7b6d2", "#7f7f7f", "#bcbd22", "#dbdb8d", "#17becf",
    "#9edae5", "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#5254a3", "#8ca252", "#bd9e39",
    "#ad494a", "#a55194", "#6b6ecf", "#b5cf6b", "#e7ba52", "#d6616b", "#ce6dbd", "#3182bd",
]
ALL_CLASSES = tuple(dict.fromkeys(BEDROOM_CLASSES + LIVING_DINING_CLASSES))
PALETTE: dict[str, tuple[int, int, int]] = {
    name: tuple(int(_PALETTE_HEX[i][k:k + 2], 16) for k in (1, 3, 5)) for i, name in enumerate(ALL_CLASSES)
}
BACKGROUND = (255, 255, 255)
FLOOR = (222, 222, 222)
WALL = (60, 60, 60)
COLLISION = (230, 0, 0)
OUT_OF_BOUND = (200, 0, 200)
UNREACHABLE = (255, 140, 0)
OFF_FLOOR = (0, 70, 255)


@dataclass
class Overlays:
    """What to mark on a render: object indices that collide, leave the floor plan or do not stand on the
    floor (sunk into it or lifted off it), and an unreachable
    floor mask ``(grid, xs, zs)`` (``grid[i, j]`` True where the cell at z = zs[i], x = xs[j] is free
    floor that cannot be reached)."""

    colliding: Sequence[int] = field(default_factory=list)
    out_of_bound: Sequence[int] = field(default_factory=list)
    off_floor: Sequence[int] = field(default_factory=list)
    unreachable: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def _view(layout: Layout, extent: float | None) -> tuple[np.ndarray, float]:
    centre = layout.floor.centre
    if extent is None:
        xmin, zmin, xmax, zmax = layout.floor.bounds
        extent = 0.5 * max(xmax - xmin, zmax - zmin) * 1.08 + 0.1
    return centre, extent


def render_layout(layout: Layout, size: int = 256, extent: float | None = None, overlays: Overlays | None = None,
                  legend: bool = False, title: str | None = None, show_front: bool = True) -> np.ndarray:
    """Render one layout top-down as an ``(H, W, 3)`` uint8 array.

    ``extent`` is the half width in metres of the square view around the floor's centre (default: fit the
    room); a fixed extent keeps the metric scale identical across images, as FID/KID renders need.
    ``legend`` appends a strip naming the classes present; ``title`` adds a caption line.
    """
    centre, ext = _view(layout, extent)
    scale = size / (2 * ext)

    def px(xz: np.ndarray) -> list[tuple[float, float]]:
        p = (np.asarray(xz) - centre) * scale + size / 2
        return [(float(a), float(b)) for a, b in p]

    img = Image.new("RGB", (size, size), BACKGROUND)
    draw = ImageDraw.Draw(img)
    draw.polygon(px(layout.floor.vertices), fill=FLOOR, outline=WALL, width=max(1, size // 128))

    if overlays is not None and overlays.unreachable is not None:
        grid, xs, zs = overlays.unreachable
        r = max(scale * (xs[1] - xs[0]) / 2 if len(xs) > 1 else 1.0, 0.5)
        for i, j in zip(*np.nonzero(grid)):
            (x0, z0), = px(np.array([[xs[j], zs[i]]]))
            draw.rectangle([x0 - r, z0 - r, x0 + r, z0 + r], fill=UNREACHABLE)

    corners = layout.footprints()
    tops = layout.translations[:, 1] + layout.half_sizes[:, 1]
    ceiling = np.array([lbl in CEILING_CLASSES for lbl in layout.labels], dtype=bool)
    order = [k for k in np.argsort(tops, kind="stable") if not ceiling[k]] + list(np.nonzero(ceiling)[0])
    colliding = set(overlays.colliding) if overlays else set()
    outside = set(overlays.out_of_bound) if overlays else set()
    line = max(1, size // 200)
    for k in order:
        colour = PALETTE[layout.labels[k]]
        poly = px(corners[k])
        if ceiling[k]:
            draw.polygon(poly, outline=colour, width=2 * line)
            continue
        draw.polygon(poly, fill=colour, outline=tuple(int(c * 0.6) for c in colour), width=line)
        if show_front:
            t, h, yaw = layout.translations[k], layout.half_sizes[k], layout.yaws[k]
            front = box_corners_xz(t[[0, 2]], np.array([h[0] * 0.5, h[2]]), np.array(yaw))[[2, 3]]
            draw.line(px(front), fill=(30, 30, 30), width=2 * line)
    for k in sorted(colliding | outside):
        draw.polygon(px(corners[k]), outline=COLLISION if k in colliding else OUT_OF_BOUND, width=3 * line)
    for k in overlays.off_floor if overlays else ():
        a, b, c, d = px(corners[k])
        draw.line([a, c], fill=OFF_FLOOR, width=2 * line)
        draw.line([b, d], fill=OFF_FLOOR, width=2 * line)

    if legend or title:
        img = _decorate(img, layout, legend, title)
    return np.asarray(img)


def _decorate(img: Image.Image, layout: Layout, legend: bool, title: str | None) -> Image.Image:
    font = ImageFont.load_default()
    size = img.height
    labels = sorted(set(layout.labels), key=layout.labels.index) if legend else []
    width = size + (130 if legend else 0)
    top = 14 if title else 0
    canvas = Image.new("RGB", (width, max(size, 14 * len(labels) + 4) + top), BACKGROUND)
    canvas.paste(img, (0, top))
    draw = ImageDraw.Draw(canvas)
    if title:
        draw.text((3, 1), title, fill=(0, 0, 0), font=font)
    for i, name in enumerate(labels):
        y = top + 4 + 14 * i
        draw.rectangle([size + 6, y, size + 16, y + 10], fill=PALETTE[name])
        draw.text((size + 20, y - 1), name, fill=(0, 0, 0), font=font)
    return canvas


def image_grid(images: Sequence[np.ndarray], cols: int, titles: Sequence[str] | None = None,
               pad: int = 4) -> np.ndarray:
    """Tile images (any sizes) into one ``(H, W, 3)`` array, ``cols`` per row, with optional captions."""
    if not images:
        raise ValueError("no images to tile")
    font = ImageFont.load_default()
    cap = 14 if titles else 0
    h = max(im.shape[0] for im in images) + cap
    w = max(im.shape[1] for im in images)
    rows = (len(images) + cols - 1) // cols
    canvas = Image.new("RGB", (cols * (w + pad) + pad, rows * (h + pad) + pad), BACKGROUND)
    draw = ImageDraw.Draw(canvas)
    for i, im in enumerate(images):
        x, y = pad + (i % cols) * (w + pad), pad + (i // cols) * (h + pad)
        if titles:
            draw.text((x + 2, y), str(titles[i])[: w // 6], fill=(0, 0, 0), font=font)
        canvas.paste(Image.fromarray(im), (x, y + cap))
    return np.asarray(canvas)


def palette_legend(classes: Sequence[str], width: int = 200) -> np.ndarray:
    """A legend image listing ``classes`` with their colours."""
    font = ImageFont.load_default()
    img = Image.new("RGB", (width, 14 * len(classes) + 6), BACKGROUND)
    draw = ImageDraw.Draw(img)
    for i, name in enumerate(classes):
        y = 4 + 14 * i
        draw.rectangle([4, y, 14, y + 10], fill=PALETTE[name])
        draw.text((18, y - 1), name, fill=(0, 0, 0), font=font)
    return np.asarray(img)


def save_image(image: np.ndarray, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)
    return path
