"""A straightforward reference of the metrics and universal rewards, for tests and benchmarks only:
one shapely polygon per footprint, a Python loop over object pairs and over scenes. Slow on purpose
(clarity over speed); the library's batched code in ``iarcs_env.geometry`` must agree with it."""

from __future__ import annotations

import numpy as np
import shapely
from scipy import ndimage
from shapely.geometry import Polygon

from iarcs_env.rooms import CEILING_CLASSES
from iarcs_env.scene import Layout, box_corners_xz


def footprint(layout: Layout, k: int, shrink: float = 0.0) -> Polygon:
    half = np.maximum(layout.half_sizes[k, [0, 2]] - shrink, 0.0)
    return Polygon(box_corners_xz(layout.translations[k, [0, 2]], half, np.array(layout.yaws[k])))


def ground(layout: Layout) -> list[int]:
    return [k for k, lbl in enumerate(layout.labels) if lbl not in CEILING_CLASSES]


def overlap_volume(layout: Layout, i: int, j: int) -> float:
    area = footprint(layout, i).intersection(footprint(layout, j)).area
    ti, hi = layout.translations[i, 1], layout.half_sizes[i, 1]
    tj, hj = layout.translations[j, 1], layout.half_sizes[j, 1]
    return area * max(0.0, min(ti + hi, tj + hj) - max(ti - hi, tj - hj))


def collisions(layout: Layout, threshold: float = 1e-6) -> tuple[set[int], float]:
    """Colliding ground objects and the total overlap volume of ground pairs."""
    g = ground(layout)
    hit, total = set(), 0.0
    for a, i in enumerate(g):
        for j in g[a + 1:]:
            v = overlap_volume(layout, i, j)
            total += v
            if v > threshold:
                hit.update((i, j))
    return hit, total


def out_areas(layout: Layout, shrink: float = 0.05) -> list[float]:
    floor = layout.floor.polygon
    out = []
    for k in range(len(layout)):
        fp = footprint(layout, k, shrink)
        out.append(fp.area - fp.intersection(floor).area)
    return out


def walkable(layout: Layout, cell: float = 0.05, radius: float = 0.3) -> dict:
    """Free grid, largest 4-connected component, reachable ground objects, mean clearance."""
    floor = layout.floor.polygon
    xmin, zmin, xmax, zmax = layout.floor.bounds
    w = int(np.ceil((xmax - xmin) / cell - 1e-9))
    h = int(np.ceil((zmax - zmin) / cell - 1e-9))
    xs = xmin + (np.arange(w) + 0.5) * cell
    zs = zmin + (np.arange(h) + 0.5) * cell
    gx, gz = np.meshgrid(xs, zs)
    pts = shapely.points(gx, gz)
    free = shapely.contains(floor, pts) & (shapely.distance(floor.exterior, pts) >= radius)
    blocked = {}
    for k in ground(layout):
        blocked[k] = shapely.distance(footprint(layout, k), pts) < radius
        free &= ~blocked[k]
    labels, n = ndimage.label(free)
    if n:
        sizes = np.bincount(labels.ravel())[1:]
        largest = labels == (np.argmax(sizes) + 1)
    else:
        largest = np.zeros_like(free)
    near = ndimage.binary_dilation(largest, structure=np.ones((3, 3), dtype=bool))
    reach = {k: bool((m & near).any()) for k, m in blocked.items()}
    n_free = int(free.sum())
    dist = ndimage.distance_transform_edt(np.pad(free, 1)) [1:-1, 1:-1] * cell
    return {"free": free, "largest": largest, "n_free": n_free, "n_largest": int(largest.sum()), "regions": n,
            "walkable": largest.sum() / n_free if n_free else 0.0, "reach": reach,
            "clearance": float(dist[free].mean()) if n_free else 0.0,
            "floor_cells": int((shapely.contains(floor, pts) & (shapely.distance(floor.exterior, pts) >= radius)).sum())}


def metrics(layouts: list[Layout], cell: float = 0.05, radius: float = 0.3) -> dict:
    objects = grounds = colliding = scenes_col = out = reach = 0
    walk = []
    for lay in layouts:
        hit, _ = collisions(lay)
        objects += len(lay)
        grounds += len(ground(lay))
        colliding += len(hit)
        scenes_col += bool(hit)
        out += sum(a > 1e-5 for a in out_areas(lay))
        wk = walkable(lay, cell, radius)
        reach += sum(wk["reach"].values())
        walk.append(wk["walkable"])
    return {"Col_obj": colliding / max(grounds, 1), "Col_scene": scenes_col / len(layouts),
            "R_out": out / max(objects, 1), "R_reach": reach / max(grounds, 1), "R_walkable": float(np.mean(walk))}


# --- rewards ---------------------------------------------------------------------------------------------
def collision_reward(layout: Layout) -> float:
    hit, total = collisions(layout)
    return 1.0 if not hit else -total


def boundary_reward(layout: Layout, shrink: float = 0.05) -> float:
    areas = out_areas(layout, shrink)
    return 2.0 if all(a <= 1e-5 for a in areas) else -float(sum(areas))


def accessibility_reward(layout: Layout, cell: float = 0.1, radius: float = 0.3) -> float:
    wk = walkable(layout, cell, radius)
    coverage = wk["n_largest"] / wk["floor_cells"] if wk["floor_cells"] else 0.0
    return 1.0 * coverage - 0.1 * wk["regions"] + 0.5 * wk["clearance"]
