"""The embedded procedural generator: determinism, valid rooms, placement rules, flaws and realism."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from iarcs_env.datasets import load_layouts
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.datasets.realism import class_kl, count_tvd, flaw_rates, median_area, nonrect_fraction
from iarcs_env.floorplan import FloorPlan
from iarcs_env.rooms import CEILING_CLASSES, get_room
from iarcs_env.scene import box_corners_xz

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "3dfront"
ROOMS = ("bedroom", "livingroom", "diningroom")


@pytest.fixture(scope="module")
def clean_bedrooms():
    return generate_layouts("bedroom", 200, seed=3, flaw_rate=0.0)


@pytest.fixture(scope="module")
def flawed_bedrooms():
    return generate_layouts("bedroom", 300, seed=0, flaw_rate=1.0)


def _footprints(lay):
    return [Polygon(c) for c in box_corners_xz(lay.translations[:, [0, 2]], lay.half_sizes[:, [0, 2]], lay.yaws)]


def _same(a, b):
    return (a.labels == b.labels and a.id == b.id and np.array_equal(a.translations, b.translations)
            and np.array_equal(a.half_sizes, b.half_sizes) and np.array_equal(a.yaws, b.yaws)
            and np.array_equal(a.floor.vertices, b.floor.vertices) and a.ceiling_height == b.ceiling_height)


@pytest.mark.parametrize("room", ROOMS)
def test_deterministic_for_a_seed(room):
    a = generate_layouts(room, 20, seed=7)
    b = generate_layouts(room, 20, seed=7)
    c = generate_layouts(room, 20, seed=8)
    assert all(_same(x, y) for x, y in zip(a, b))
    assert not all(_same(x, y) for x, y in zip(a, c))
    # each scene has its own stream: a shorter run is a prefix of a longer one
    assert all(_same(x, y) for x, y in zip(generate_layouts(room, 5, seed=7), a[:5]))
    assert a[3].id == f"procedural-{room}-00003"


@pytest.mark.parametrize("room", ROOMS)
def test_rooms_are_valid(room):
    spec = get_room(room)
    layouts = generate_layouts(room, 150, seed=1)
    counts = []
    for lay in layouts:
        assert lay.room_type == spec.name
        FloorPlan.from_vertices(lay.floor.vertices)  # validates: simple polygon, positive area
        assert np.allclose(lay.floor.centre, 0.0, atol=1e-6)  # centred at the origin
        assert set(lay.labels) <= set(spec.classes)
        assert len(lay) <= spec.max_objects
        assert np.all(lay.half_sizes > 0)
        assert np.all((lay.yaws >= -math.pi) & (lay.yaws < math.pi))
        ground = np.array([l not in CEILING_CLASSES for l in lay.labels], dtype=bool)
        # floor objects stand on the floor; lamps hang from the ceiling
        assert np.allclose(lay.translations[ground, 1], lay.half_sizes[ground, 1], atol=1e-3)
        top = lay.translations[~ground, 1] + lay.half_sizes[~ground, 1]
        assert np.all(top <= lay.ceiling_height + 1e-6) and np.all(top >= lay.ceiling_height - 0.06)
        counts.append(len(lay))
    assert np.mean(counts) > (3 if room == "bedroom" else 6)


def test_bedroom_shapes_and_areas():
    layouts = generate_layouts("bedroom", 300, seed=2)
    frac = nonrect_fraction(layouts)
    assert 0.3 <= frac <= 0.5
    shapes = {len(l.floor.vertices) for l in layouts}
    assert {4, 6, 8} <= shapes  # rectangles, L shapes, U / two-corner shapes
    areas = np.array([l.floor.area for l in layouts])
    assert 10.5 < np.median(areas) < 15.5
    assert areas.min() >= 6.5 and np.percentile(areas, 95) < 30


def test_sizes_follow_furniture_standards(flawed_bedrooms):
    def sizes(label):
        return np.array([2 * l.half_sizes[k] for l in flawed_bedrooms for k, x in enumerate(l.labels) if x == label])

    bed = sizes("double_bed")
    assert np.all((bed[:, 0] >= 1.2) & (bed[:, 0] <= 2.3)) and np.all((bed[:, 2] >= 1.9) & (bed[:, 2] <= 2.4))
    ns = sizes("nightstand")
    assert np.all((ns[:, 0] >= 0.4) & (ns[:, 0] <= 0.6)) and np.all((ns[:, 1] >= 0.45) & (ns[:, 1] <= 0.65))
    wd = sizes("wardrobe")
    assert np.all((wd[:, 2] >= 0.55) & (wd[:, 2] <= 0.65)) and np.all(wd[:, 0] <= 2.4)
    assert np.all((wd[:, 1] >= 2.0) & (wd[:, 1] <= 2.4))
    assert wd[:, 0].std() > 0.15  # varied, not one template


def test_flawless_rooms_have_no_overlaps_and_stay_inside():
    for room in ROOMS:
        for lay in generate_layouts(room, 120, seed=5, flaw_rate=0.0):
            floor = lay.floor.polygon
            foot = _footprints(lay)
            for k, p in enumerate(foot):
                assert p.difference(floor).area < 1e-9, (lay.id, lay.labels[k])
            ground = [k for k, l in enumerate(lay.labels) if l not in CEILING_CLASSES]
            for i, a in enumerate(ground):
                for b in ground[i + 1:]:
                    assert foot[a].intersection(foot[b]).area < 1e-9, (lay.id, lay.labels[a], lay.labels[b])
    assert flaw_rates(generate_layouts("bedroom", 100, seed=6, flaw_rate=0.0)) == \
        {"Col_obj": 0.0, "Col_scene": 0.0, "R_out": 0.0}


def test_bed_head_against_wall_and_nightstands_beside_it(clean_bedrooms):
    n_beds = n_ns = 0
    for lay in clean_bedrooms:
        walls = lay.floor.polygon.exterior
        beds = [k for k, l in enumerate(lay.labels) if l in ("double_bed", "single_bed", "kids_bed")]
        for b in beds:
            x, _, z = lay.translations[b]
            hx, _, hz = lay.half_sizes[b]
            s, c = math.sin(lay.yaws[b]), math.cos(lay.yaws[b])
            head = Point(x - s * hz, z - c * hz)  # middle of the head end (local -z)
            foot = Point(x + s * hz, z + c * hz)
            assert walls.distance(head) <= 0.035, lay.id
            assert walls.distance(foot) > 0.3, lay.id  # the bed faces into the room
            n_beds += 1
            for k, label in enumerate(lay.labels):
                if label != "nightstand":
                    continue
                d = lay.translations[k, [0, 2]] - np.array([x, z])
                if np.linalg.norm(lay.translations[k, [0, 2]] - np.array([head.x, head.y])) > hx + 0.7:
                    continue  # a nightstand elsewhere in the room
                along_front = d @ np.array([s, c])
                along_side = d @ np.array([c, -s])
                # beside the head: level with the bed's head end, just off one side, facing the same way
                assert abs(lay.yaws[k] - lay.yaws[b]) < 1e-6
                assert abs(along_front - (-hz + lay.half_sizes[k, 2])) < 0.02
                assert hx < abs(along_side) < hx + lay.half_sizes[k, 0] * 2 + 0.1
                n_ns += 1
    assert n_beds > 150 and n_ns > 0.9 * n_beds


def test_rooms_follow_placement_rules(clean_bedrooms):
    """Wardrobes stand against a wall facing in; desks have a chair in front facing them; TV stands face
    the bed; dining chairs face their table; lamps hang over the floor."""
    checked = {"wardrobe": 0, "desk_chair": 0, "tv": 0}
    for lay in clean_bedrooms:
        walls = lay.floor.polygon.exterior
        for k, label in enumerate(lay.labels):
            x, _, z = lay.translations[k]
            s, c = math.sin(lay.yaws[k]), math.cos(lay.yaws[k])
            hz = lay.half_sizes[k, 2]
            if label in ("wardrobe", "desk", "tv_stand", "cabinet", "dressing_table"):
                assert walls.distance(Point(x - s * hz, z - c * hz)) <= 0.035, (lay.id, label)
                assert lay.floor.contains(x + s * (hz + 0.1), z + c * (hz + 0.1))  # faces into the room
                checked["wardrobe"] += label == "wardrobe"
            if label == "tv_stand" and "double_bed" in lay.labels:
                b = lay.labels.index("double_bed")
                to_bed = lay.translations[b, [0, 2]] - np.array([x, z])
                if to_bed @ np.array([s, c]) > 0.5 * np.linalg.norm(to_bed):
                    checked["tv"] += 1
            if label == "desk" and "chair" in lay.labels:
                chairs = [j for j, l in enumerate(lay.labels) if l == "chair"]
                ahead = [j for j in chairs if np.linalg.norm(
                    lay.translations[j, [0, 2]] - (np.array([x, z]) + np.array([s, c]) * (hz + 0.3))) < 0.35]
                if ahead:
                    j = ahead[0]
                    assert abs(abs(lay.yaws[j] - lay.yaws[k]) - math.pi) < 1e-6  # facing the desk
                    checked["desk_chair"] += 1
    assert checked["wardrobe"] > 60 and checked["desk_chair"] >= 5 and checked["tv"] >= 10
    # dining chairs face their table
    n = 0
    dining = generate_layouts("diningroom", 40, seed=4, flaw_rate=0.0)
    assert sum("dining_table" in lay.labels for lay in dining) >= 38
    for lay in dining:
        if lay.labels.count("dining_table") != 1:
            continue
        t = lay.labels.index("dining_table")
        for j, label in enumerate(lay.labels):
            if label == "dining_chair":
                to_t = lay.translations[t, [0, 2]] - lay.translations[j, [0, 2]]
                front = np.array([math.sin(lay.yaws[j]), math.cos(lay.yaws[j])])
                if np.linalg.norm(to_t) < 1.6:
                    assert to_t @ front > 0.5 * np.linalg.norm(to_t)
                    n += 1
    assert n > 100


def test_flaws_at_real_rates(flawed_bedrooms):
    r = flaw_rates(flawed_bedrooms)
    # real bedroom_val: Col_obj 41%, Col_scene 56%, R_out 7%
    assert 0.25 <= r["Col_obj"] <= 0.55
    assert 0.35 <= r["Col_scene"] <= 0.75
    assert 0.03 <= r["R_out"] <= 0.13
    half = flaw_rates(generate_layouts("bedroom", 300, seed=0, flaw_rate=0.5))
    assert 0 < half["Col_obj"] < r["Col_obj"] and 0 < half["R_out"] < r["R_out"]
    liv = flaw_rates(generate_layouts("livingroom", 80, seed=0, flaw_rate=1.0))
    assert liv["Col_scene"] > 0.4  # chairs pushed under dining tables
    assert 0 < liv["R_out"] < 0.05  # real livingroom_val: 1.5%


def test_load_layouts_procedural_and_arguments():
    lays = load_layouts("procedural", "bedroom", num_scenes=4, seed=1)
    assert len(lays) == 4 and all(l.room_type == "bedroom" for l in lays)
    assert generate_layouts("bedroom", 0) == []
    with pytest.raises(ValueError, match="flaw_rate"):
        generate_layouts("bedroom", 2, flaw_rate=1.5)
    with pytest.raises(ValueError, match="unknown room type"):
        generate_layouts("kitchen", 2)


def test_realism_figure_definitions():
    a = generate_layouts("bedroom", 30, seed=0)
    assert count_tvd(a, a) == 0.0 and class_kl(a, a) == pytest.approx(0.0, abs=1e-12)
    # beds per room: rooms without a bed against the same rooms, counted on beds only
    beds = ("double_bed", "single_bed", "kids_bed")
    no_bed = [replace(l, labels=["wardrobe" if lbl in beds else lbl for lbl in l.labels]) for l in a]
    with_bed = sum(any(lbl in beds for lbl in l.labels) for l in a) / len(a)
    assert count_tvd(a, no_bed, beds) == pytest.approx(with_bed) and count_tvd(a, a, beds) == 0.0
    assert median_area(a) == pytest.approx(np.median([l.floor.area for l in a]))
    # the KL is finite when the generator misses a class, and positive
    b = [l for l in a if "wardrobe" not in l.labels]
    assert 0 < class_kl(a, b) < 1


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real 3D-FRONT layouts not present at {REAL}")
def test_realism_against_real_bedrooms(flawed_bedrooms):
    from iarcs_env.datasets.json_format import read_json_layouts

    real = read_json_layouts(REAL / "bedroom_val.json")
    gen = generate_layouts("bedroom", 500, seed=0)
    assert count_tvd(real, gen) <= 0.15
    assert class_kl(real, gen) <= 0.10
    assert abs(median_area(gen) / median_area(real) - 1) <= 0.2
    assert abs(nonrect_fraction(gen) - nonrect_fraction(real)) <= 0.1


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real 3D-FRONT layouts not present at {REAL}")
def test_realism_against_real_living_rooms():
    from iarcs_env.datasets.json_format import read_json_layouts

    real = read_json_layouts(REAL / "livingroom_val.json")
    gen = generate_layouts("livingroom", 500, seed=0)
    assert count_tvd(real, gen) <= 0.15
    assert class_kl(real, gen) <= 0.05
    assert abs(median_area(gen) / median_area(real) - 1) <= 0.2
