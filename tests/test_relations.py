"""Batched relations (iarcs_env.relations) against a per-object shapely reference on random rooms."""

import numpy as np
import pytest
import shapely
import torch
from shapely.geometry import LineString, Point

from iarcs_env import relations as rel
from iarcs_env.metrics import batch_float64
from scene_factory import random_layouts
from shapely_reference import footprint


@pytest.fixture(scope="module")
def rooms():
    layouts = [lay.centred() for lay in random_layouts(12, seed=3, max_objects=6, spread=0.6)]
    return layouts, batch_float64(layouts)


def test_footprint_gap_matches_shapely(rooms):
    layouts, b = rooms
    gap = rel.footprint_gap(b.translations, b.half_sizes, b.yaws)
    for s, lay in enumerate(layouts):
        for i in range(len(lay)):
            for j in range(len(lay)):
                ref = footprint(lay, i).distance(footprint(lay, j))
                assert float(gap[s, i, j]) == pytest.approx(ref, abs=1e-9), (s, i, j)


def test_wall_distance_and_back_to_wall_match_shapely(rooms):
    layouts, b = rooms
    edges = rel.floor_edges(b.floors)
    wall = rel.wall_distance(b.translations, b.half_sizes, b.yaws, edges)
    back = rel.back_to_wall(b.translations, b.half_sizes, b.yaws, edges)
    for s, lay in enumerate(layouts):
        floor = lay.floor.polygon
        for k in range(len(lay)):
            fp = footprint(lay, k)
            inside = floor.contains(Point(lay.translations[k, [0, 2]]))
            ref = fp.distance(floor.exterior) if inside else 0.0
            assert float(wall[s, k]) == pytest.approx(ref, abs=1e-9), (s, k)
            # back edge midpoint, ray backwards
            f = np.array([np.sin(lay.yaws[k]), np.cos(lay.yaws[k])])
            p = lay.translations[k, [0, 2]] - f * lay.half_sizes[k, 2]
            if floor.contains(Point(p)):
                hit = LineString([p, p - 100 * f]).intersection(floor.exterior)
                ref = min(Point(p).distance(g) for g in shapely.get_parts(hit))
                assert float(back[s, k]) == pytest.approx(ref, abs=1e-9), (s, k)
            elif not floor.exterior.distance(Point(p)) < 1e-9:
                assert float(back[s, k]) < 0


def test_class_mask_and_groups():
    labels = torch.tensor([[0, 8, 12, 21]])  # armchair, double_bed, nightstand, empty (bedroom)
    from iarcs_env.rooms import get_room

    classes = get_room("bedroom").classes
    assert rel.class_mask(labels, classes, ["bed"]).tolist() == [[False, True, False, False]]
    assert rel.class_mask(labels, classes, ["seat", "table"]).tolist() == [[True, False, True, False]]
    assert rel.class_mask(labels, classes, ["any"]).tolist() == [[True, True, True, False]]
    assert rel.class_mask(labels, classes, ["wine_cabinet"]).sum() == 0
    with pytest.raises(ValueError, match="unknown object class or group 'beds'"):
        rel.class_mask(labels, classes, ["beds"])
    for group in rel.CLASS_GROUPS.values():
        assert set(group) <= set(rel.ALL_CLASSES)
