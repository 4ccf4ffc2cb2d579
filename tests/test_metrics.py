"""The paper's metrics (iarcs_env.metrics / iarcs_env.geometry): hand-made scenes with known answers,
agreement with a per-pair shapely reference on random scenes, the reference figures of real
3D-FRONT bedrooms, and a prior's bed ablation (agents/bed_ablation.py)."""

from pathlib import Path

import numpy as np
import pytest
import torch

import shapely_reference as ref
from iarcs_env import geometry as geo
from iarcs_env.metrics import (HEADLINE, batch_float64, class_kl, count_distance, evaluate_batch,
                               evaluate_layouts, footprint_change)
from scene_factory import L_SHAPE, RECT, box, make_layout, random_layouts

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "3dfront" / "bedroom_val.json"


def run(layout, **kw):
    return evaluate_batch(batch_float64([layout]), **kw)


# --- collisions ---------------------------------------------------------------------------------------
def test_touching_boxes_do_not_collide_overlapping_boxes_do():
    touching = make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 2.0, 1.5, 0.5, 0.3)])
    r = run(touching)
    assert not r.colliding.any() and r.overlap.max() < 1e-12
    overlapping = make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 1.9, 1.5, 0.5, 0.3)])
    r = run(overlapping)
    assert r.colliding[0].tolist() == [True, True]
    assert r.overlap[0, 0, 1] == pytest.approx(0.1 * 0.6 * 0.8, abs=1e-12)
    out = evaluate_layouts([touching, overlapping])
    assert out["Col_obj"] == pytest.approx(0.5) and out["Col_scene"] == pytest.approx(0.5)


def test_rotated_square_overlap_has_the_known_area():
    # a 1 m square and the same square turned 45 degrees: a regular octagon of area 2 (sqrt 2 - 1)
    sq = torch.tensor([[[0.0, 0.0]]], dtype=torch.float64)
    half = torch.tensor([[[0.5, 0.5]]], dtype=torch.float64)
    p = geo.box_corners_xz(sq[0], half[0], torch.tensor([0.0], dtype=torch.float64))
    q = geo.box_corners_xz(sq[0], half[0], torch.tensor([np.pi / 4], dtype=torch.float64))
    assert geo.convex_overlap_area(p, q).item() == pytest.approx(2 * (np.sqrt(2) - 1), abs=1e-12)
    lay = make_layout([box("table", 2, 1.5, 0.5, 0.5, 0.0, hy=0.5), box("desk", 2, 1.5, 0.5, 0.5, np.pi / 4, hy=0.5)])
    assert run(lay).overlap[0, 0, 1] == pytest.approx(2 * (np.sqrt(2) - 1) * 1.0, abs=1e-12)


def test_stacked_boxes_at_different_heights_do_not_collide():
    lay = make_layout([box("cabinet", 2, 1.5, 0.5, 0.3, y0=0.0, hy=0.4),
                       box("shelf", 2, 1.5, 0.5, 0.3, y0=0.8, hy=0.3),      # sits exactly on top
                       box("bookshelf", 2, 1.5, 0.5, 0.3, y0=1.5, hy=0.2)])  # above, with a gap
    assert not run(lay).colliding.any()


def test_lamp_inside_a_bed_box_is_not_a_collision():
    bed = box("double_bed", 2, 1.5, 1.0, 1.1, hy=0.5)
    lamp = ("pendant_lamp", (2, 0.8, 1.5), (0.3, 0.3, 0.3), 0.0)  # overlaps the bed's box in 3D
    r = run(make_layout([bed, lamp]))
    assert r.ground[0].tolist() == [True, False]
    assert not r.colliding.any()
    out = evaluate_layouts([make_layout([bed, lamp])])
    assert out["Col_obj"] == 0 and out["n_ground_objects"] == 1 and out["n_objects"] == 2
    assert out["mean_objects"] == 2 and out["mean_ground_objects"] == 1  # the lamp is no furniture


# --- out of bound -------------------------------------------------------------------------------------
def test_object_half_through_an_l_shaped_wall_has_the_known_out_area():
    # the inner wall z = 2 for x in [2, 4]; the box spans z 1.5..2.5, shrunk 1.55..2.45, x 2.55..3.45
    through = box("wardrobe", 3.0, 2.0, 0.5, 0.5)
    corner = box("cabinet", 2.0, 2.0, 0.5, 0.5)  # centred on the reflex corner: one quarter outside
    inside = box("nightstand", 1.0, 1.0, 0.3, 0.3)
    r = run(make_layout([through, corner, inside], floor=L_SHAPE))
    assert r.out_area[0, 0] == pytest.approx(0.9 * 0.45, abs=1e-12)
    assert r.out_area[0, 1] == pytest.approx(0.45 * 0.45, abs=1e-12)
    assert r.out_area[0, 2] == 0
    assert r.out_of_bound[0].tolist() == [True, True, False]
    out = evaluate_layouts([make_layout([through, corner, inside], floor=L_SHAPE)])
    assert out["R_out"] == pytest.approx(2 / 3)


def test_flush_against_the_wall_is_not_out_of_bound_thanks_to_the_shrink():
    lay = make_layout([box("wardrobe", 0.52, 1.5, 0.55, 0.3)])  # 3 cm through the wall x = 0
    assert not run(lay).out_of_bound.any()
    lay = make_layout([box("wardrobe", 0.40, 1.5, 0.55, 0.3)])  # 15 cm through: 10 cm after the shrink
    r = run(lay)
    assert r.out_of_bound[0, 0] and r.out_area[0, 0] == pytest.approx(0.10 * 0.5, abs=1e-12)


# --- floor contact -----------------------------------------------------------------------------------
def test_sunk_and_lifted_furniture_is_off_the_floor_but_lamps_and_small_gaps_are_not():
    objects = [box("double_bed", 1.0, 1.5, 0.9, 1.0, y0=-0.15),   # sunk 0.15 m into the floor
               box("nightstand", 2.4, 0.5, 0.25, 0.25, y0=0.3),   # lifted 0.3 m
               box("wardrobe", 3.4, 2.5, 0.5, 0.3, y0=0.04),      # 4 cm: within the 5 cm tolerance
               box("cabinet", 3.4, 1.2, 0.3, 0.3),                # on the floor
               ("pendant_lamp", (2.0, 1.8, 1.5), (0.2, 0.2, 0.2), 0.0)]  # hangs: not a ground object
    r = run(make_layout(objects))
    assert r.off_floor[0].tolist() == [True, True, False, False, False]
    out = evaluate_layouts([make_layout(objects)], keep_scenes=True)
    assert out["R_off_floor"] == pytest.approx(2 / 4)
    assert out["scenes"][0].off_floor == [0, 1] and out["scenes"][0].has_issue


# --- wall alignment ------------------------------------------------------------------------------------
def test_furniture_turned_away_from_the_walls_is_misaligned_whatever_the_quarter_turn():
    deg = np.pi / 180
    objects = [box("double_bed", 1.0, 1.5, 0.9, 1.0, yaw=20 * deg),       # 20 degrees off: misaligned
               box("nightstand", 2.4, 0.5, 0.25, 0.25, yaw=95 * deg),     # a quarter turn + 5: aligned
               box("wardrobe", 3.4, 2.5, 0.5, 0.3, yaw=-172 * deg),       # 8 off a half turn: aligned
               box("cabinet", 3.4, 1.2, 0.3, 0.3, yaw=45 * deg),          # diagonal: misaligned
               ("pendant_lamp", (2.0, 1.8, 1.5), (0.2, 0.2, 0.2), 0.3)]  # hangs: not a ground object
    lay = make_layout(objects)
    b = batch_float64([lay])
    angles = geo.wall_misalignment(b.yaws, b.floors, b.ground_mask)[0]
    assert angles.tolist() == pytest.approx([20, 5, 8, 45, 0], abs=1e-9)
    assert run(lay).misaligned[0].tolist() == [True, False, False, True, False]
    assert evaluate_layouts([lay])["R_misaligned"] == pytest.approx(2 / 4)
    # a floor turned 30 degrees: furniture turned with it is aligned
    turn = 30 * deg
    c, s = np.cos(turn), np.sin(turn)
    floor = [(c * x - s * z, s * x + c * z) for x, z in RECT]
    aligned = make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3, yaw=-turn)], floor=floor)
    assert not run(aligned).misaligned.any()
    assert run(make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3)], floor=floor)).misaligned[0, 0]


# --- walkability and reachability ---------------------------------------------------------------------
def test_a_wardrobe_splitting_the_room_gives_the_known_walkable_ratio_and_reach():
    # room 4 x 3; a wardrobe wall-to-wall at x = 1.4..1.6; free x: 0.3..1.1 (left) and 1.9..3.7 (right)
    objects = [box("wardrobe", 1.5, 1.5, 0.1, 1.5, hy=1.0),
               box("nightstand", 0.25, 1.5, 0.2, 0.2),   # only reachable from the small left part
               box("double_bed", 3.0, 1.5, 0.5, 0.5)]    # in the large right part
    r = run(make_layout(objects))
    left, right = 0.8 * 2.4, 1.8 * 2.4
    # the nightstand (inflated) and the bed (inflated) remove cells from both parts
    assert r.walkable[0] == pytest.approx(r.largest_cells[0] / r.free_cells[0])
    grid = r.space.scene_grid(0)
    xs = grid["xs"] + 2.0  # grids are in the centred frame: the 4 x 3 room's centre is (2, 1.5)
    assert grid["largest"][:, xs < 1.5].sum() == 0 and grid["free"][:, xs < 1.5].sum() > 0
    bed_inflated = np.pi * 0.09 + 4 * 0.3 + 1.0 * 1.0  # rounded square of side 1 grown by 0.3
    stand_inflated = (0.45 + 0.05) * 0.4 + 0.3 * 0.4 + (np.pi * 0.09) / 2  # clipped at the wall side
    expected = (right - bed_inflated) / (right - bed_inflated + left - stand_inflated + 0.05 * 0.8)
    assert r.walkable[0] == pytest.approx(expected, abs=0.03)
    assert r.reachable[0].tolist() == [True, False, True]
    out = evaluate_layouts([make_layout(objects)])
    assert out["R_reach"] == pytest.approx(2 / 3)
    # the unreachable mask marks the left part only
    res = evaluate_layouts([make_layout(objects)], keep_scenes=True, keep_masks=True)["scenes"][0]
    mask, mxs, _ = res.unreachable
    assert mask.any() and mask[:, mxs + 2.0 > 1.5].sum() == 0 and res.unreachable_objects == [1]


def test_nothing_free_gives_zero_walkability_and_no_reach():
    lay = make_layout([box("wardrobe", 2, 1.5, 1.9, 1.4)], floor=RECT)
    r = run(lay)
    assert r.free_cells[0] == 0 and r.walkable[0] == 0 and not r.reachable.any()


def test_empty_room_is_fully_walkable():
    r = run(make_layout([("ceiling_lamp", (2, 2.4, 1.5), (0.3, 0.1, 0.3), 0.0)]))
    assert r.walkable[0] == 1.0
    # free cells: centres at least 0.3 m from the walls of the 4 x 3 room
    assert r.free_cells[0] == pytest.approx((3.4 / 0.05) * (2.4 / 0.05), rel=0.03)


# --- agreement with the per-pair shapely reference ---------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_batched_metrics_agree_with_the_shapely_reference(seed):
    layouts = random_layouts(24, seed=seed)
    res = evaluate_batch(batch_float64(layouts))
    for b, lay in enumerate(layouts):
        lay = lay.centred()
        hit, total = ref.collisions(lay)
        assert set(np.nonzero(res.colliding[b])[0]) == hit
        assert np.triu(res.overlap[b], 1).sum() == pytest.approx(total, abs=1e-9)
        areas = np.array(ref.out_areas(lay))
        np.testing.assert_allclose(res.out_area[b][: len(lay)], areas, atol=1e-9)
        wk = ref.walkable(lay)
        grid = res.space.scene_grid(b)
        assert (grid["free"] == wk["free"]).all()
        assert res.largest_cells[b] == wk["n_largest"]
        assert {k: bool(res.reachable[b, k]) for k in wk["reach"]} == wk["reach"]
    summary = evaluate_layouts(layouts)
    expected = ref.metrics([lay.centred() for lay in layouts])
    for key in HEADLINE:
        assert summary[key] == pytest.approx(expected[key], abs=1e-12)


def test_headline_keys_are_fractions_and_set_statistics():
    layouts = random_layouts(12, seed=3)
    out = evaluate_layouts(layouts, reference=layouts)
    for key in HEADLINE:
        assert 0.0 <= out[key] <= 1.0
    assert out["KL_class"] == pytest.approx(0.0, abs=1e-12) and out["count_distance"] == 0.0
    fewer = [make_layout([box("double_bed", 2, 1.5, 0.8, 1.0)])] * 12
    assert class_kl(layouts, fewer) > 1.0
    assert count_distance(layouts, fewer) == pytest.approx(np.mean([len(l) for l in layouts]) - 1)
    assert out["footprint_change"] == pytest.approx(0.0, abs=1e-12)


def test_footprint_change_is_the_geometric_mean_area_ratio_class_by_class():
    def rooms(bed_half, stand_half, n=6):
        bed, stand = box("double_bed", 2, 1.5, bed_half, bed_half), box("nightstand", 0.5, 0.5, stand_half, stand_half)
        return [make_layout([bed, stand, box("wardrobe", 3, 2.5, 0.3, 0.3)] if i else [bed]) for i in range(n)]
    reference = rooms(1.0, 0.25)
    # beds 10% narrower and shorter (area x 0.81), nightstands unchanged, 5 wardrobes only in the reference
    generated = [make_layout([box("double_bed", 2, 1.5, 0.9, 0.9), box("nightstand", 0.5, 0.5, 0.25, 0.25)])] * 6
    change = footprint_change(reference, generated)
    assert change["by_class"] == pytest.approx({"double_bed": -0.19, "nightstand": 0.0})
    assert change["all"] == pytest.approx(np.sqrt(0.81) - 1)  # 6 beds and 6 nightstands: half the log-ratio
    # a class needs min_objects on both sides: the wardrobes (5) count only with min_objects <= 5
    assert "wardrobe" not in footprint_change(reference, reference, min_objects=6)["by_class"]


def test_mixed_room_types_are_refused():
    a = make_layout([box("double_bed", 2, 1.5, 0.8, 1.0)])
    b = make_layout([box("dining_table", 2, 1.5, 0.8, 0.5)], room="diningroom")
    with pytest.raises(ValueError, match="room types"):
        evaluate_layouts([a, b])


# --- real 3D-FRONT bedrooms ---------------------------------------------------------------------------
@pytest.mark.skipif(not REAL.exists(), reason=f"real 3D-FRONT layouts not available at {REAL.resolve()}")
def test_real_bedrooms_land_on_the_reference_figures():
    from iarcs_env.datasets import load_layouts

    out = evaluate_layouts(load_layouts(REAL))
    # ../shared/data/3dfront/README.md: Col_obj 41.4%, Col_scene 55.8%, R_out 7.3%, R_reach 78.6%, R_walkable 0.915
    assert out["n_scenes"] == 500 and out["n_objects"] == 2335
    assert out["Col_obj"] == pytest.approx(0.414, abs=0.02)
    assert out["Col_scene"] == pytest.approx(0.558, abs=0.02)
    assert out["R_out"] == pytest.approx(0.073, abs=0.02)
    assert out["R_reach"] == pytest.approx(0.786, abs=0.02)
    assert out["R_walkable"] == pytest.approx(0.915, abs=0.02)
    assert out["R_off_floor"] < 0.002  # real ground objects stand on the floor: 2 of 1,863 are 5-9 cm off it
    assert out["R_misaligned"] == pytest.approx(0.028, abs=0.005)  # 53 of 1,863 turned > 10 deg from the walls


def test_bed_ablation_removes_only_the_bed_and_measures_from_it():
    """agents/bed_ablation.py (issue 37's "the denoiser uses the bed"): only rooms with one bed and a nightstand
    count; emptying the bed's slot moves the restored nightstands of a network that attends across slots;
    distances out from the bed's side; the nightstands of every noise draw pooled."""
    from agents.bed_ablation import bed_ablation
    from agents.denoiser import ScenePrior
    from conftest import perturb_zero_init
    from iarcs_env.env import default_stats

    torch.manual_seed(0)
    prior = perturb_zero_init(ScenePrior.create("bedroom", default_stats("bedroom"), "tiny"))
    bed = box("double_bed", 2.0, 1.05, 0.8, 1.0)  # x from 1.2 to 2.8
    left, right = box("nightstand", 3.05, 0.5, 0.2, 0.2), box("nightstand", 0.95, 0.5, 0.2, 0.2)  # 0.25 m out
    rooms = [make_layout([bed, left]), make_layout([bed, left, right]),
             make_layout([bed, box("single_bed", 3.6, 3.0, 0.45, 0.9), left]), make_layout([bed])]
    f = bed_ablation(prior, rooms, [1], noise_draws=2)[1]
    assert (f["rooms"], f["nightstands"], f["kept"], f["noise_draws"]) == (2, 3, 2 * 3, 2)
    assert f["out_from_side_truth"] == pytest.approx([0.25, 0.25, 0.25], abs=1e-3)
    assert f["error_with_bed_m"] < 0.05 and f["moved_by_removing_bed_m"] > 0
    assert f["ratio"] == pytest.approx(f["error_with_bed_m"] / f["error_without_bed_m"])
    assert f["bed_error_m"] < 0.05 and f["error_from_restored_bed_m"] < 0.1  # t = 1: the bed restored where it was
