"""Hand-made and random layouts for the metric, reward and distribution tests."""

from __future__ import annotations

import numpy as np

from iarcs_env.floorplan import FloorPlan
from iarcs_env.rooms import get_room
from iarcs_env.scene import Layout

RECT = [(0, 0), (4, 0), (4, 3), (0, 3)]
L_SHAPE = [(0, 0), (4, 0), (4, 2), (2, 2), (2, 4), (0, 4)]


def make_layout(objects, floor=RECT, room="bedroom", id="test") -> Layout:
    """``objects``: list of (label, (x, y, z) centre, (hx, hy, hz) half size, yaw)."""
    labels = [o[0] for o in objects]
    return Layout(room, FloorPlan.from_vertices(floor), labels,
                  np.array([o[1] for o in objects], dtype=float).reshape(-1, 3),
                  np.array([o[2] for o in objects], dtype=float).reshape(-1, 3),
                  np.array([o[3] for o in objects], dtype=float), id=id)


def box(label, x, z, hx, hz, yaw=0.0, y0=0.0, hy=0.4):
    """A box standing at height ``y0`` (its bottom)."""
    return (label, (x, y0 + hy, z), (hx, hy, hz), yaw)


def random_layouts(n: int, seed: int = 0, room: str = "bedroom", max_objects: int = 10,
                   spread: float = 1.0) -> list[Layout]:
    """Random rooms (rectangles and L shapes, randomly rotated and shifted) with random boxes, some of
    them crossing walls or each other. Coordinates are generic floats (no ties at exact distances)."""
    rng = np.random.default_rng(seed)
    spec = get_room(room)
    out = []
    for i in range(n):
        w, d = rng.uniform(2.5, 6.0, 2)
        if rng.random() < 0.5:
            poly = np.array([(0, 0), (w, 0), (w, d), (0, d)])
        else:
            a, b = rng.uniform(0.3, 0.7, 2)
            poly = np.array([(0, 0), (w, 0), (w, b * d), (a * w, b * d), (a * w, d), (0, d)])
        yaw = rng.uniform(-np.pi, np.pi)
        c, s = np.cos(yaw), np.sin(yaw)
        poly = poly @ np.array([[c, -s], [s, c]]) + rng.uniform(-3, 3, 2)
        floor = FloorPlan.from_vertices(poly)
        k = int(rng.integers(1, max_objects + 1))
        labels = list(rng.choice(spec.classes, k))
        xmin, zmin, xmax, zmax = floor.bounds
        cx = rng.uniform(xmin, xmax, k)
        cz = rng.uniform(zmin, zmax, k)
        half = np.stack([rng.uniform(0.1, 1.0, k) * spread, rng.uniform(0.1, 0.9, k), rng.uniform(0.1, 1.0, k) * spread], 1)
        cy = half[:, 1] + rng.uniform(0, 0.4, k) * (rng.random(k) < 0.3)
        yaws = rng.uniform(-np.pi, np.pi, k)
        out.append(Layout(room, floor, labels, np.stack([cx, cy, cz], 1), half, yaws, id=f"random_{i}"))
    return out
