"""Realism figures: how closely a set of layouts matches a reference set (the procedural generator vs the
real 3D-FRONT files), shared by ``tests/test_procedural.py`` and ``benchmarks/bench_realism.py``.

* **Object-count TVD**: total-variation distance between the normalised histograms of objects per room,
  ``TVD(p, q) = 1/2 * sum_k |p_k - q_k|`` over counts k = 0, 1, ... (0: identical, 1: disjoint).
* **Class KL**: ``KL(real || generated) = sum_c p_c * log(p_c / q_c)`` over the room type's classes, where
  ``p`` and ``q`` are the class frequencies (objects of class c / all objects) each smoothed as
  ``(f_c + eps) / (1 + K * eps)`` with ``eps = 1e-3`` so that a class the generator never makes costs a
  large but finite amount.
* **Median area**: median floor-polygon area (m^2); compared as the ratio generated / real.
* **Non-rectangular fraction**: rooms whose floor is not a single rectangle.
* **Flaw rates** (the definitions of :mod:`iarcs_env.metrics`, a plain shapely reference): Col_obj (colliding ground objects
  / ground objects; two ground objects collide when their oriented boxes overlap by more than 1e-6 m^3),
  Col_scene (rooms with a collision / rooms) and R_out (objects whose footprint, shrunk by 0.05 m per
  side, has more than 1e-5 m^2 outside the floor / all objects). Boxes rotate about y only, so the
  overlap volume is the footprint intersection area times the vertical overlap.
"""

from __future__ import annotations

from collections import Counter
from typing import Sequence

import numpy as np
import shapely
from shapely.geometry import Polygon

from ..rooms import CEILING_CLASSES, get_room
from ..scene import Layout, box_corners_xz

#: Smoothing of class frequencies in :func:`class_kl`.
KL_EPS = 1e-3


def object_counts(layouts: Sequence[Layout], classes=None) -> np.ndarray:
    """Objects per room (of ``classes`` only, when given)."""
    return np.array([len(l) if classes is None else sum(lbl in classes for lbl in l.labels) for l in layouts],
                    dtype=int)


def count_histogram(layouts: Sequence[Layout], max_count: int | None = None, classes=None) -> np.ndarray:
    """Normalised histogram of objects (of ``classes``) per room over 0..max_count (default: the largest count)."""
    counts = object_counts(layouts, classes)
    n = max_count if max_count is not None else int(counts.max(initial=0))
    h = np.bincount(np.minimum(counts, n), minlength=n + 1).astype(float)
    return h / max(h.sum(), 1.0)


def count_tvd(real: Sequence[Layout], generated: Sequence[Layout], classes=None) -> float:
    """Total-variation distance between the histograms of objects (of ``classes``: e.g. beds) per room (0 best,
    1 worst)."""
    n = int(max(object_counts(real, classes).max(initial=0), object_counts(generated, classes).max(initial=0)))
    return float(0.5 * np.abs(count_histogram(real, n, classes) - count_histogram(generated, n, classes)).sum())


def class_frequencies(layouts: Sequence[Layout], classes: Sequence[str] | None = None) -> np.ndarray:
    """Fraction of all objects in each class, in the order of ``classes`` (default: the room's list)."""
    if classes is None:
        classes = get_room(layouts[0].room_type).classes
    c = Counter(lbl for l in layouts for lbl in l.labels)
    f = np.array([c.get(k, 0) for k in classes], dtype=float)
    return f / max(f.sum(), 1.0)


def class_kl(real: Sequence[Layout], generated: Sequence[Layout], classes: Sequence[str] | None = None,
             eps: float = KL_EPS) -> float:
    """KL(real || generated) of the smoothed class frequencies (nats; 0 best). See the module docstring."""
    if classes is None:
        classes = get_room(real[0].room_type).classes
    p = class_frequencies(real, classes) + eps
    q = class_frequencies(generated, classes) + eps
    p, q = p / p.sum(), q / q.sum()
    return float(np.sum(p * np.log(p / q)))


def median_area(layouts: Sequence[Layout]) -> float:
    """Median floor area in m^2."""
    return float(np.median([l.floor.area for l in layouts]))


def nonrect_fraction(layouts: Sequence[Layout]) -> float:
    """Fraction of rooms whose floor polygon is not a rectangle."""
    return float(np.mean([not l.floor.is_rectangle for l in layouts])) if layouts else 0.0


def flaw_rates(layouts: Sequence[Layout], shrink: float = 0.05) -> dict[str, float]:
    """Col_obj, Col_scene and R_out (:mod:`iarcs_env.metrics` definitions) with shapely; a reference, not fast."""
    n_ground = n_col = n_col_scene = n_obj = n_out = 0
    for lay in layouts:
        floor = lay.floor.polygon
        corners = box_corners_xz(lay.translations[:, [0, 2]], lay.half_sizes[:, [0, 2]], lay.yaws)
        small = box_corners_xz(lay.translations[:, [0, 2]], np.maximum(lay.half_sizes[:, [0, 2]] - shrink, 0),
                               lay.yaws)
        foot = shapely.polygons(corners) if len(lay) else []
        for k in range(len(lay)):
            n_obj += 1
            if Polygon(small[k]).difference(floor).area > 1e-5:
                n_out += 1
        ground = [k for k, lbl in enumerate(lay.labels) if lbl not in CEILING_CLASSES]
        lo = lay.translations[:, 1] - lay.half_sizes[:, 1]
        hi = lay.translations[:, 1] + lay.half_sizes[:, 1]
        hit = set()
        for a_i, a in enumerate(ground):
            for b in ground[a_i + 1:]:
                dy = min(hi[a], hi[b]) - max(lo[a], lo[b])
                if dy <= 0:
                    continue
                if foot[a].intersection(foot[b]).area * dy > 1e-6:
                    hit.update((a, b))
        n_ground += len(ground)
        n_col += len(hit)
        n_col_scene += bool(hit)
    return {"Col_obj": n_col / max(n_ground, 1), "Col_scene": n_col_scene / max(len(layouts), 1),
            "R_out": n_out / max(n_obj, 1)}


def realism_figures(real: Sequence[Layout], generated: Sequence[Layout]) -> dict[str, float]:
    """All the comparison figures of generated layouts against real ones, as one dict."""
    return {
        "count_tvd": count_tvd(real, generated),
        "class_kl": class_kl(real, generated),
        "median_area_real": median_area(real),
        "median_area_generated": median_area(generated),
        "area_ratio": median_area(generated) / median_area(real),
        "mean_count_real": float(np.mean([len(l) for l in real])),
        "mean_count_generated": float(np.mean([len(l) for l in generated])),
        "nonrect_real": nonrect_fraction(real),
        "nonrect_generated": nonrect_fraction(generated),
    }


__all__ = ["KL_EPS", "class_frequencies", "class_kl", "count_histogram", "count_tvd", "flaw_rates",
           "median_area", "nonrect_fraction", "realism_figures"]
