"""Tests of the analysis scripts' own logic (not of the product: tests/ covers that, and imports nothing here).
Run by hand, not by ``make test``::

    .venv/bin/python -m pytest research/
"""

from __future__ import annotations

import copy
import importlib.util
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))  # the hand-made layouts of tests/scene_factory.py

from agents.denoiser import ScenePrior  # noqa: E402
from iarcs_env.relations import BEDS  # noqa: E402
from scene_factory import L_SHAPE, box, make_layout  # noqa: E402


def load(name: str):
    """research/<name>.py as a module, loaded from its file (research/ is a folder of scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(f"research_{name}", HERE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny models run fastest (and reproducibly) on one torch thread; the setting is restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


rl = load("relation_learning")


# --- eval_prior.py, relation_fidelity.py, class_counts.py, out_of_bound_remedies.py ------------------------
def test_eval_prior_lists_the_colliding_class_pairs_with_their_overlap():
    """research/eval_prior.py --collision-pairs: which pairs collide, and by how much."""
    script = load("eval_prior")
    # a nightstand 0.1 m into the bed (0.1 x 0.5 x 0.8 m of overlap), a chair clear of both, a lamp above
    tucked = make_layout([box("double_bed", 1.5, 1.5, 1.0, 1.0), box("nightstand", 2.65, 1.5, 0.25, 0.25),
                          box("chair", 3.6, 0.4, 0.2, 0.2)])
    clear = make_layout([box("double_bed", 1.5, 1.5, 1.0, 1.0), box("nightstand", 2.8, 1.5, 0.25, 0.25)])
    res = script.collision_pairs([tucked, clear])
    assert res["pairs"] == 1 and res["counts"] == {"double_bed - nightstand": 1}
    assert res["overlap_m3_quartiles"][1] == pytest.approx(0.1 * 0.5 * 0.8, rel=1e-4)
    assert script.collision_pairs([clear])["pairs"] == 0


def test_collision_pairs_separates_nightstand_bed_contact_from_other_collisions():
    script = load("collision_pairs")
    # a nightstand 0.07 m into its bed (0.028 m^3: the data's kind of contact), a chair 0.15 m into a desk
    tucked = make_layout([box("double_bed", 1.5, 1.5, 1.0, 1.0), box("nightstand", 2.68, 1.5, 0.25, 0.25),
                          box("chair", 3.6, 0.4, 0.2, 0.2)])
    desk = make_layout([box("desk", 1.0, 1.0, 0.6, 0.3), box("chair", 1.0, 1.4, 0.25, 0.25)])
    res = script.collisions([tucked, desk])
    assert res["Col_obj"] == pytest.approx(4 / 5) and res["only_contact"] == pytest.approx(2 / 5)
    assert res["Col_obj_beyond_contact"] == pytest.approx(2 / 5)  # the contact is spared, the chair is not
    assert {k: len(v) for k, v in res["pairs"].items()} == {("double_bed", "nightstand"): 1, ("chair", "desk"): 1}
    assert res["volumes"] == pytest.approx([0.07 * 0.5 * 0.8], rel=1e-4)
    deeper = make_layout([box("double_bed", 1.5, 1.5, 1.0, 1.0), box("nightstand", 2.6, 1.5, 0.25, 0.25)])
    assert script.collisions([deeper])["Col_obj_beyond_contact"] == 1  # 0.064 m^3: more than the data's contact
    # in a dining room the seat-table contact is spared up to 0.11 m^3: the chair 0.15 m into its desk (0.045)
    assert script.collisions([desk], "diningroom")["Col_obj_beyond_contact"] == 0
    # with every other collision cleared, only the bed and its nightstand would still collide
    assert res["Col_obj_contact_kept"] == pytest.approx(2 / 5)
    # a chair tucked under its desk stays colliding; a second chair that only touches the first does not
    crowded = make_layout([box("desk", 1.0, 1.0, 0.6, 0.3), box("chair", 1.0, 1.4, 0.25, 0.25),
                           box("chair", 1.3, 1.75, 0.25, 0.25)])
    assert script.collisions([crowded], "diningroom")["Col_obj_contact_kept"] == pytest.approx(2 / 3)
    # beyond the contact: the chair 0.15 m into the desk in a bedroom (no seat-table contact there), by its depth
    assert res["beyond"] == {("chair", "desk"): [pytest.approx(0.15)]}
    # a square turned 45 degrees, another off its corner: its bounds overlap it, the oriented boxes do not
    turned = make_layout([box("wardrobe", 1.0, 1.0, 0.3, 0.3, yaw=np.pi / 4), box("cabinet", 1.55, 1.55, 0.2, 0.2)])
    apart = script.collisions([turned])
    assert apart["Col_obj"] == 0 and apart["Col_obj_by_bounds"] == 1


def test_gradient_noise_tells_signal_from_noise():
    script = load("gradient_noise")
    g = torch.Generator().manual_seed(0)
    signal = torch.randn(1, 20000, generator=g, dtype=torch.float64)
    jitter = 0.01 * torch.randn(6, 20000, generator=g, dtype=torch.float64)
    same = script.gradient_statistics(signal.expand(6, -1) + jitter)
    assert same["cosine"] > 0.99 and same["signal_share"] == pytest.approx(1, abs=0.01)
    noise = script.gradient_statistics(torch.randn(6, 20000, generator=g, dtype=torch.float64))
    assert abs(noise["cosine"]) < 0.02 and abs(noise["signal_share"]) < 0.02
    half = script.gradient_statistics(signal + torch.randn(6, 20000, generator=g, dtype=torch.float64))
    assert half["signal_share"] == pytest.approx(0.5, abs=0.03) and half["cosine"] == pytest.approx(0.5, abs=0.03)


def test_eval_prior_reports_task_success_per_row():
    """research/eval_prior.py --tasks: each row gets the five checkers' rates, printed in percent."""
    script = load("eval_prior")
    low = make_layout([box("double_bed", 1.5, 1.5, 1.0, 1.0, hy=0.3)])        # top at 0.6 m: reach_1m holds
    high = make_layout([box("wardrobe", 1.5, 0.4, 0.5, 0.3, hy=1.0)])         # top at 2.0 m: it does not
    rows = {"two rooms": {}, "untested": {}}
    script.add_task_success(rows["two rooms"], [low, high])
    assert set(rows["two rooms"]["tasks"]) == {"reach_1m", "tv_from_bed", "study_zone", "two_nightstands",
                                               "wheelchair"}
    assert rows["two rooms"]["tasks"]["reach_1m"] == 0.5 and rows["two rooms"]["tasks"]["tv_from_bed"] == 0.0
    table = script.task_table(rows).splitlines()
    assert len(table) == 3 and table[2].startswith("| two rooms | 50.0 | 0.0 |")


def test_eval_prior_position_errors_match_slots_of_the_same_class():
    """research/eval_prior.py --denoise-from: how far restored objects are from the originals."""
    from iarcs_env.scene import SceneBatch

    script = load("eval_prior")
    bed, stand = box("double_bed", 1.5, 1.5, 1.0, 1.0), box("nightstand", 2.8, 1.5, 0.25, 0.25)
    original = SceneBatch.from_layouts([make_layout([bed, stand])])
    moved = SceneBatch.from_layouts([make_layout([box("double_bed", 1.5, 1.6, 1.0, 1.0),
                                                  box("nightstand", 2.5, 1.1, 0.25, 0.25)])])
    err = script.position_errors(moved, original)
    assert err["bed"] == pytest.approx(0.1, abs=1e-5) and err["nightstand"] == pytest.approx(0.5, abs=1e-5)
    assert err["all"] == pytest.approx(0.1, abs=1e-5)  # the lower median of the two
    relabelled = SceneBatch.from_layouts([make_layout([bed, box("wardrobe", 2.5, 1.1, 0.25, 0.25)])])
    err = script.position_errors(relabelled, original)  # a slot whose class changed is not compared
    assert err["bed"] == pytest.approx(0.0, abs=1e-6) and np.isnan(err["nightstand"])


def test_relation_fidelity_takes_two_nightstands_apart():
    """research/relation_fidelity.py: rooms with a bed and 2+ nightstands, and the share of nightstands
    beside the nearest bed's head half (where the two_nightstands checker wants them)."""
    from iarcs_env.scene import SceneBatch

    script = load("relation_fidelity")
    bed = box("double_bed", 2.0, 1.05, 0.8, 1.0)  # faces +z; the headboard 0.05 m from the wall z = 0
    left, right = box("nightstand", 3.05, 0.5, 0.2, 0.2), box("nightstand", 0.95, 0.5, 0.2, 0.2)
    at_foot = box("nightstand", 3.05, 1.6, 0.2, 0.2)  # beside the foot half: not where the checker wants it
    rooms = [make_layout([bed, left, right, at_foot]), make_layout([bed, at_foot]), make_layout([left, right])]
    row = script.relation_row(SceneBatch.from_layouts(rooms))
    assert row["bed and 2+ nightstands %"] == pytest.approx(100 / 3)
    assert row["nightstands beside the head half %"] == pytest.approx(50.0)  # 2 of the 4 in rooms with a bed
    assert row["nightstands out from the side %"] == pytest.approx(100.0)  # the one at the foot is beside it too
    assert row["nightstands along the head half %"] == pytest.approx(50.0)
    assert row["nightstand out from the bed's side, m (q1, median, q3)"] == "+0.25, +0.25, +0.25"
    assert row["headboard to wall, median (m)"] == pytest.approx(0.05, abs=1e-5)
    assert row["two_nightstands %"] == pytest.approx(100 / 3)


def test_required_share_mixes_the_rooms_with_and_without_the_objects():
    script = load("required_share")
    bed = box("double_bed", 2.0, 1.05, 0.8, 1.0)
    flanked = make_layout([bed, box("nightstand", 3.05, 0.5, 0.2, 0.2), box("nightstand", 0.95, 0.5, 0.2, 0.2)])
    alone = make_layout([bed, box("wardrobe", 0.5, 3.0, 0.5, 0.3)])
    stage1, given = [alone] * 200, [flanked] * 200
    rows = script.mixtures("two_nightstands", stage1, stage1, given, [1.0, 0.5, 0.0])
    assert [r[1] for r in rows[::2]] == [1.0, 0.0] and 0.4 < rows[1][1] < 0.6  # success: the share given
    assert rows[2][2] == pytest.approx(0.0, abs=1e-6) and rows[1][2] < rows[0][2]  # KL to stage 1's own rooms
    with pytest.raises(ValueError, match="same floors"):
        script.mixtures("two_nightstands", stage1, stage1, given[:10], [1.0])


def test_relation_fidelity_counts_nightstands_overlapping_their_bed():
    """research/relation_fidelity.py: of the nightstands within 0.3 m of a bed, the share whose box overlaps it."""
    from iarcs_env.scene import SceneBatch

    script = load("relation_fidelity")
    bed = box("double_bed", 2.0, 1.05, 0.8, 1.0)  # x from 1.2 to 2.8
    tucked = box("nightstand", 3.0, 0.5, 0.25, 0.2)  # x from 2.75: 5 cm into the bed
    apart = box("nightstand", 0.9, 0.5, 0.2, 0.2)  # x up to 1.1: 10 cm from the bed
    far = box("nightstand", 4.0, 0.5, 0.2, 0.2)  # 1 m away: not next to the bed
    row = script.relation_row(SceneBatch.from_layouts([make_layout([bed, tucked, apart, far])]))
    assert row["nightstands at a bed overlapping it %"] == pytest.approx(50.0)


def test_class_counts_per_room_and_rooms_with_a_bed(tmp_path, capsys):
    """research/class_counts.py: what a run added or removed, class by class."""
    from iarcs_env.datasets import save_layouts

    script = load("class_counts")
    bed, stand = box("double_bed", 1.5, 1.5, 1.0, 1.0), box("nightstand", 2.8, 1.5, 0.25, 0.25)
    kids = box("kids_bed", 1.0, 1.0, 0.5, 0.9)
    rooms = [make_layout([bed, stand, stand]), make_layout([kids]), make_layout([stand]), make_layout([stand])]
    row = script.class_counts(rooms)
    assert row["nightstand"] == 1.0 and row["double_bed"] == 0.25 and row["kids_bed"] == 0.25
    assert row["bed (any)"] == 0.5 and row["rooms with a bed %"] == 50.0 and row["objects"] == 1.5
    save_layouts(rooms, tmp_path / "a.json")
    save_layouts(rooms[2:], tmp_path / "b.json")
    assert script.main([f"before={tmp_path / 'a.json'}", str(tmp_path / "b.json")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| per room | before | b |"
    assert "| double_bed | 0.25 | 0.00 |" in lines and "| rooms with a bed % | 50.0 | 0.0 |" in lines
    assert script.main([f"both={tmp_path / 'a.json'},{tmp_path / 'b.json'}"]) == 0  # pooled: 6 rooms, 1 double bed
    assert "| double_bed | 0.17 |" in capsys.readouterr().out.splitlines()
    # sizes: the double bed is 2 x 2 m and 0.8 m high on the floor; nightstands 0.5 x 0.5 m; one floats 0.3 m up
    assert script.class_sizes(rooms)["double_bed"] == pytest.approx((4.0, 0.0, 0.8, 0.0))
    floating = make_layout([box("nightstand", 2.8, 1.5, 0.25, 0.25, y0=0.3)] * 3)
    assert script.class_sizes([floating])["nightstand"] == pytest.approx((0.25, 0.3, 1.1, 100.0))
    lamp = make_layout([("pendant_lamp", (2.0, 1.8, 1.5), (0.2, 0.2, 0.2), 0.0)])
    assert script.class_sizes([lamp])["pendant_lamp"][3] is None  # lamps hang: no floor-contact share
    assert script.main([f"before={tmp_path / 'a.json'}", str(tmp_path / "b.json"), "--sizes", "0.2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "| double_bed | 4.00 / 0.00 / 0.80 / 0% | – |" in lines
    assert "| nightstand | 0.25 / 0.00 / 0.80 / 0% | 0.25 / 0.00 / 0.80 / 0% |" in lines
    assert "| footprints against the first file's, all classes (geometric mean) | +0.0% | +0.0% |" in lines


def test_class_counts_names_the_classes_of_the_objects_out_of_the_room(tmp_path, capsys):
    """``--out-of-bound``: a wardrobe through the notch of an L-shaped room (0.9 m x 0.45 m outside once shrunk by
    0.05 m) is out, the nightstand well inside is not; R_out's definition, class by class."""
    from iarcs_env.datasets import save_layouts

    script = load("class_counts")
    room = make_layout([box("wardrobe", 3.0, 2.0, 0.5, 0.5), box("nightstand", 1.0, 1.0, 0.3, 0.3)], floor=L_SHAPE)
    rect = make_layout([box("wardrobe", 1.0, 1.0, 0.5, 0.5)])
    counts, areas, shapes = script.out_of_bound_by_class([room, room, rect])
    assert counts == {"wardrobe": (2, 3), "nightstand": (0, 2)}
    assert shapes == {4: (1, 0, 1), 6: (2, 2, 4)}  # corners: (rooms, objects out, objects)
    assert areas == pytest.approx([0.9 * 0.45] * 2, rel=1e-6)  # the half of its 0.9 x 0.9 shrunk footprint past z = 2
    save_layouts([room], tmp_path / "l.json")
    assert script.main([str(tmp_path / "l.json"), "--out-of-bound"]) == 0
    out = capsys.readouterr().out
    assert "l: 1 objects out of bound, median area outside 0.405 m^2" in out and "| wardrobe | 1.00 | 1 / 1 |" in out
    assert "| 6 | 1 | 0.500 |" in out


def test_valid_rooms_drops_only_rooms_with_the_named_classes_out_of_bound():
    """``--out-of-bound double_bed``: a room with a nightstand through the notch is kept, one with its bed there is
    not; ``--out-of-bound`` alone drops both; with neither, a room with an object off the floor goes too."""
    script = load("valid_rooms")
    bed_out = make_layout([box("double_bed", 3.0, 2.0, 0.5, 0.5)], floor=L_SHAPE)
    stand_out = make_layout([box("double_bed", 1.0, 1.0, 0.5, 0.5), box("nightstand", 3.0, 2.0, 0.3, 0.3)],
                            floor=L_SHAPE)
    lifted = make_layout([box("double_bed", 1.0, 1.0, 0.5, 0.5, y0=0.3)])
    rooms = [bed_out, stand_out, lifted]
    assert script.valid(rooms, "bedroom", False, ["double_bed"]).tolist() == [False, True, True]
    assert script.valid(rooms, "bedroom", False, []).tolist() == [False, False, True]
    assert script.valid(rooms, "bedroom", False).tolist() == [False, False, False]


def test_narrow_gap_descent_relative_tents_charge_only_a_narrow_gap_narrowing():
    """``--relative``: a gap the room had at 0.3 m is its own tent's apex (no charge there, a charge once it narrows
    to 0.2 m), a gap it had closed or wide keeps the 0.6 m apex."""
    script = load("narrow_gap_descent")
    gaps = torch.tensor([0.3, 0.0, 1.0])
    apex = script.apexes((gaps, gaps))[0]
    assert apex.tolist() == pytest.approx([0.3, 0.6, 0.6])
    # the narrow gap kept, the closed one opened to 0.2 m charged, the wide one narrowed to 0.4 m charged
    assert script.tent(torch.tensor([0.3, 0.2, 0.4]), apex).tolist() == pytest.approx([0.0, 0.15, 0.2])
    assert script.tent(torch.tensor([0.2]), torch.tensor([0.3])).item() == pytest.approx(0.1)
    assert script.tent(torch.tensor([0.3])).item() == pytest.approx(0.25)  # the fixed tent: min(0.25, 0.3)


def test_out_of_bound_remedies_move_shrink_or_delete_each_object_and_score_the_edits():
    """research/out_of_bound_remedies.py: the wardrobe centred on the notch's edge of an L-shaped room comes
    inside by a 0.46 m shift but by no shrink down to 30%; the nightstand 0.15 m through a wall by either."""
    from iarcs_env.scene import SceneBatch
    from rewards import CompositeReward

    script = load("out_of_bound_remedies")
    room = make_layout([box("wardrobe", 3.0, 2.0, 0.5, 0.5), box("nightstand", 3.9, 1.0, 0.25, 0.25),
                        box("double_bed", 1.0, 1.0, 0.5, 0.5)], floor=L_SHAPE)
    batch = SceneBatch.from_layouts([room])
    found = script.remedies(batch)
    assert found["objects"] == [(0, 0), (0, 1)]
    moved, ok = found["moved"]
    assert ok.tolist() == [True, True]
    assert (moved.translations[0, 0] - batch.translations[0, 0]).norm().item() == pytest.approx(0.46, abs=1e-5)
    assert (moved.translations[1, 1] - batch.translations[0, 1]).norm().item() == pytest.approx(0.10, abs=1e-5)
    shrunk, ok = found["shrunk"]
    assert ok.tolist() == [False, True]
    assert shrunk.half_sizes[1, 1, 0].item() == pytest.approx(0.25 * 0.6, abs=1e-5)  # 3.9 + 0.15 - 0.05 = 4
    deleted, ok = found["deleted"]
    assert ok.all() and deleted.mask.sum(1).tolist() == [2, 2]
    result = script.score(CompositeReward({"boundary": 1.0}), batch, found)
    assert result["shrunk"]["n"] == 1 and result["moved"]["n"] == 2
    for edit in script.EDITS:  # every edit takes one of two objects out of the walls: the bonus stays out of reach
        assert result[edit]["improved"] == 1.0 and result[edit]["terms"]["boundary"] > 0


# --- reward_spread.py ---------------------------------------------------------------------------------------
def test_reward_spread_measures_the_spread_within_floor_groups():
    """research/reward_spread.py: a term that differs only between floors has no within-floor spread
    (it cannot move a per-floor advantage), one that differs inside each floor has its own std."""
    spread = load("reward_spread").within_floor_std
    floor = torch.tensor([0, 0, 1, 1])
    assert spread(torch.tensor([1.0, 1.0, 5.0, 5.0]), floor) == 0.0
    assert spread(torch.tensor([0.0, 2.0, 4.0, 8.0]), floor) == pytest.approx((1.0 + 2.0) / 2)


# --- relation_learning.py -----------------------------------------------------------------------------------
def test_reduced_rooms():
    rooms = rl.reduced_rooms(160, seed=3)
    assert all(len(lay.floor.vertices) == 4 for lay in rooms)
    assert all(set(lay.labels) <= set(rl.KEPT) and sum(label in BEDS for label in lay.labels) == 1 for lay in rooms)
    assert all(len(lay.labels) == len(lay.translations) == len(lay.yaws) == len(lay.extras) for lay in rooms)
    assert [lay.id for lay in rl.reduced_rooms(20, seed=3)] == [lay.id for lay in rooms[:20]]  # a stream per seed
    data = rl.figures(rooms)
    assert data["beds_per_room"] == {"1": 1.0} and data["one_bed"] == 1.0
    assert 0.2 < data["bed_and_2_nightstands"] < 0.8 and data["two_nightstands_given"] > 0.9


def test_variants_combine():
    assert rl.variant_options("present") == {"model": {}}
    assert rl.variant_options("slot_identity+min_snr") == {"model": {"slot_embedding": True}, "canonical_order": True,
                                                           "permutation_augment": False, "loss_weighting": "min_snr"}
    with pytest.raises(ValueError, match="unknown variant"):
        rl.variant_options("present+nope")


@pytest.mark.parametrize("variant", ["present", "slot_identity+classes_given+x0+min_snr"])
def test_the_script_runs_end_to_end(tmp_path, variant):
    args = ["--variant", variant, "--minutes", "0.02", "0.04", "--train-rooms", "40", "--heldout", "8",
            "--preset", "tiny", "--layers", "1", "--batch-size", "8", "--quiet", "--out", str(tmp_path / "run"),
            "--json", str(tmp_path / "rows.json")]
    rl.main(args)
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["budget_minutes"] for r in rows] == [0.02, 0.04]
    assert 0 < rows[0]["steps"] < rows[1]["steps"]
    for row in rows:
        assert row["rooms_seen"] == 8 * row["steps"] and row["variant"] == variant
        assert row["data"] == rows[0]["data"] and row["data"]["rooms"] == 8 and row["samples"]["rooms"] == 8
        assert row["beds_per_room_tv"] == pytest.approx(rl.total_variation(row["samples"]["beds_per_room"],
                                                                          row["data"]["beds_per_room"]))
        prior = ScenePrior.load(row["prior"])
        if variant != "present":  # the options reached the prior
            assert prior.denoiser.config.slot_embedding and prior.schedule.config.prediction_type == "sample"
            assert prior.meta["classes_given"] and row["samples"]["beds_per_room"] == row["data"]["beds_per_room"]
    with pytest.raises(SystemExit, match="holds a run"):
        rl.main(args)
    rl.main(["--plot", str(tmp_path / "rows.json"), "--png", str(tmp_path / "curves.png")])
    assert (tmp_path / "curves.png").stat().st_size > 1000


def test_repeat_draws_conditions_the_second_draw_on_the_first():
    repeat_rates = load("repeat_draws").repeat_rates
    first = np.array([True, True, False, False, False])
    second = np.array([True, False, True, False, False])
    rates = repeat_rates(first, second)
    assert rates["first"] == 0.4 and rates["second"] == 0.4
    assert rates["second | first passed"] == 0.5 and rates["second | first failed"] == pytest.approx(1 / 3)
    assert rates["both failed"] == 0.4
    with pytest.raises(ValueError, match="sample the same floors twice"):
        repeat_rates(first, second[:4])


def test_chair_placement_measures_each_chairs_gap_and_facing():
    script = load("chair_placement")
    room = make_layout([box("dining_table", 2.0, 2.0, 0.6, 0.4),
                        box("dining_chair", 2.0, 1.4, 0.2, 0.2),                # touching, facing it (+z)
                        box("dining_chair", 2.0, 2.9, 0.2, 0.2, yaw=np.pi),     # 0.3 m away, facing it
                        box("dining_chair", 3.5, 0.5, 0.2, 0.2)],               # far from it
                       room="diningroom")
    res = script.chair_placement([room, make_layout([box("dining_chair", 1.0, 1.0, 0.2, 0.2)], room="diningroom")])
    assert res["rooms"] == 1 and res["holds"] == 1.0 and res["chairs"] == 3 and res["at_table"] == 2
    assert res["touching"] == pytest.approx(1 / 3) and res["near"] == pytest.approx(2 / 3)
    assert res["pulled_out"] == pytest.approx(2 / 3)
    assert res["facing_near"] == 1.0 and res["gap_median"] == pytest.approx(0.3)
    assert script.chair_placement([room], chairs=("armchair",))["rooms"] == 0  # no armchair: no room counted


def test_chair_placement_restores_the_rooms_with_a_prior(tmp_path, capsys):
    """--restore: the data's rooms noised to t and restored by a prior; the shipped dining prior's last step keeps
    the chairs at their tables (holds 99.8% on the 500 seed-777 rooms)."""
    from iarcs_env.datasets import save_layouts
    from iarcs_env.datasets.procedural import generate_layouts

    script = load("chair_placement")
    save_layouts(generate_layouts("diningroom", 12, seed=777), tmp_path / "d.json")
    script.main([f"data={tmp_path / 'd.json'}", "--room", "diningroom", "--restore",
                 str(ScenePrior.default_path("diningroom")), "--from-t", "0"])
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()[2:]]
    assert [r[0] for r in rows] == ["| data", "| data, restored from t = 0"]
    assert rows[0][1] == rows[1][1] and float(rows[1][2].rstrip("%")) >= 75.0  # the same rooms; the chairs kept


def test_skip_prediction_errors_per_class_add_up_to_the_rooms_objects():
    """centre_errors on 12 procedural dining rooms and the shipped dining prior: at t = 0 with no noise the input is the
    rooms themselves (scaled by sqrt(abar_0)), x0_hat is off by centimetres, and the per-class counts are the rooms' objects."""
    from agents.pretrain_data import SceneTensors, encode_batch
    from iarcs_env.datasets.procedural import generate_layouts

    script = load("skip_prediction")
    prior = ScenePrior.load_default("diningroom")
    rooms = generate_layouts("diningroom", 12, seed=777)
    data = SceneTensors.from_layouts(rooms, prior.num_slots)
    x0, floor = encode_batch(prior.spec, prior.stats, *data.batch(torch.arange(len(rooms))))
    hat, noisy, _, shares, by_class = script.centre_errors(prior, x0, floor, data.extents, torch.zeros_like(x0), 0)
    assert noisy < 1e-3 and 0 < hat < 0.3 and abs(sum(shares.values()) - 1) < 1e-6
    assert sum(count for count, _ in by_class.values()) == sum(len(room) for room in rooms)
    assert by_class["dining_table"][0] == sum(room.labels.count("dining_table") for room in rooms)


def test_adapter_capacity_grows_the_task_adapter_without_changing_what_it_predicts():
    """grow(): the wheelchair config's adapter (a copy of stage 1's rank-16 attention LoRA) grown to rank 32 on the
    attention and feed-forward layers predicts the same x0_hat, and has the new layers' and ranks' weights to train."""
    from agents.train import load_train_config
    from iarcs_env.datasets.procedural import generate_layouts

    script = load("adapter_capacity")  # puts research/ on the path
    from descent_offline import build_with_targets

    cfg = load_train_config(str(HERE.parent / "experiments/ablations/task_wheelchair_gradient.yaml"))
    _, policy = build_with_targets(cfg)
    prior, g = policy.prior, torch.Generator().manual_seed(0)
    floors = [lay.centred().floor for lay in generate_layouts("bedroom", 4, seed=777)]
    x0 = prior.sample_features(floors, 4, 1.0, g)
    t, cond, classes = torch.full((4,), 100), prior.floor_condition(floors), x0[..., 8:].argmax(-1)
    x_t = prior.schedule.q_sample(x0, t, torch.randn(x0.shape, generator=g))
    with torch.no_grad():
        before = policy.predict_x0(x_t, t, cond, classes)
        script.grow(policy, cfg.adapter, "init", 32, r".*\.(q_proj|k_proj|v_proj|out_proj|ff\.[03])$")
        after = policy.predict_x0(x_t, t, cond, classes)
    assert torch.allclose(before, after, atol=1e-5)
    ranks = {k: v.shape[0] for k, v in policy.model.state_dict().items() if f"lora_A.{cfg.adapter}." in k}
    assert set(ranks.values()) == {32} and any(".ff.0." in k for k in ranks) and len(ranks) == 60


def test_object_moves_reads_each_class_move_and_what_it_cost_from_report_pairs(tmp_path):
    from iarcs_env.datasets import save_layouts

    script = load("object_moves")
    table = box("dining_table", 2.0, 1.5, 0.6, 0.4)
    before = [make_layout([table, box("dining_chair", 2.0, 0.9, 0.2, 0.2), box("cabinet", 3.5, 0.3, 0.4, 0.2)],
                          room="diningroom"),
              make_layout([table], room="diningroom")]
    after = [make_layout([table, box("dining_chair", 2.0, 0.6, 0.2, 0.2), box("cabinet", 3.9, 0.3, 0.4, 0.2)],
                         room="diningroom"),
             make_layout([table, box("dining_chair", 1.0, 1.0, 0.2, 0.2)], room="diningroom")]  # not paired
    reports = []
    for name, rooms, scored in (("base", before, [([], []), ([], [])]), ("run", after, [([1], [2]), ([], [])])):
        save_layouts(rooms, tmp_path / f"{name}.json")
        report = {"scenes_file": f"{name}.json", "room_type": "diningroom",
                  "per_scene": [{"unreachable_objects": u, "out_of_bound": o} for u, o in scored]}
        (tmp_path / f"{name}_report.json").write_text(json.dumps(report))
        reports.append(tmp_path / f"{name}_report.json")
    rows, paired = script.object_moves([tuple(reports)])
    assert paired == 1 and rows["dining_table"]["objects"] == 2
    assert rows["dining_chair"]["mean_move"] == pytest.approx(0.3)
    assert rows["cabinet"]["mean_move"] == pytest.approx(0.4)
    assert rows["dining_table"]["mean_move"] == 0.0
    assert (rows["dining_chair"]["unreachable_base"], rows["dining_chair"]["unreachable_run"]) == (0, 1)
    assert (rows["cabinet"]["out_base"], rows["cabinet"]["out_run"]) == (0, 1)


def test_object_moves_bins_the_lost_walkway_by_the_base_rooms_walkable_share_and_counts_split_rooms(tmp_path):
    script = load("object_moves")
    scored = {"base": [(1.0, []), (0.97, [2]), (0.5, [1, 2, 3]), (0.96, [])],
              "run": [(0.6, [1, 4]), (0.99, [2]), (0.8, [1]), (0.92, [])]}  # room 0 split; 3 stays above 0.9
    paths = []
    for name, rooms in scored.items():
        report = {"per_scene": [{"R_walkable": w, "unreachable_objects": u} for w, u in rooms]}
        (tmp_path / f"{name}.json").write_text(json.dumps(report))
        paths.append(tmp_path / f"{name}.json")
    rows, split = script.reach_by_walkable([tuple(paths)])
    assert [r["rooms"] for r in rows] == [1, 0, 0, 0, 3]  # walkable 1.0 falls in the last bin
    assert (rows[0]["unreachable_base"], rows[0]["unreachable_run"]) == (3, 1)
    assert (rows[-1]["unreachable_base"], rows[-1]["unreachable_run"]) == (1, 3)
    assert split == 1


def test_gradient_vs_count_compares_prior_and_adapter_on_the_same_noise(tmp_path):
    from conftest import write_tiny_train_config
    from experiments.cli import main

    config = write_tiny_train_config(tmp_path, algorithm="physics-gradient", epochs=1,
                                     ddpo={"samples_per_floor": 4, "minibatch_size": 8, "gradient_steps": 2,
                                           "learning_rate": 0.05, "overlap_measure": "depth"})
    assert main(["train", "--config", str(config)]) == 0
    prior, adapter = load("gradient_vs_count").compare(str(tmp_path / "run"), num_floors=4)
    assert (prior["policy"], adapter["policy"]) == ("prior", "adapter")
    for row in (prior, adapter):
        assert len(row["x0_hat"]) == 4 and row["final"] > 0 and 0 <= row["Col_obj"] <= 1
    again = load("gradient_vs_count").compare(str(tmp_path / "run"), num_floors=4)[0]
    assert again == prior  # same floors, same noise


def test_metric_trade_reads_reports_in_percent_and_draws_them(tmp_path):
    mt = load("metric_trade")
    for name, col, reach in (("a", 0.5, 0.8), ("b", 0.25, 0.7)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"Col_obj": col, "R_reach": reach}))
    pts = mt.points([f"prior={tmp_path / 'a.json'}", f"depth, 30 epochs={tmp_path / 'b.json'}"], "Col_obj", "R_reach")
    assert pts == [("prior", 50.0, 80.0), ("depth, 30 epochs", 25.0, 70.0)]  # a label may hold commas and spaces
    from PIL import Image

    png = mt.plot(pts, "Col_obj", "R_reach", str(tmp_path / "trade.png"))
    pixels = Image.open(png).convert("L")
    assert pixels.size == (720, 440) and pixels.getextrema() == (0, 255)  # something drawn on white
    with pytest.raises(SystemExit, match="no R_walkable"):
        mt.points([f"a={tmp_path / 'a.json'}"], "Col_obj", "R_walkable")
    for name, col, reach, objects, ground in (("c", 0.5, 0.8, 100, 50), ("d", 0.2, 0.6, 300, 150)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"Col_obj": col, "R_reach": reach, "n_objects": objects,
                                                           "n_ground_objects": ground}))
    (point,) = mt.points([f"two samplings={tmp_path / 'c.json'},{tmp_path / 'd.json'}"], "Col_obj", "R_reach")
    assert point == ("two samplings", pytest.approx(27.5), pytest.approx(65.0))  # weighed by objects, ground objects


def test_seat_desk_pulls_push_a_chair_out_of_its_desk_forward_unless_the_pair_is_uncharged():
    from iarcs_env.env import default_stats

    room = make_layout([box("desk", 2.0, 0.35, 0.6, 0.3), box("chair", 2.0, 0.75, 0.25, 0.25),  # 0.15 m into it
                        box("double_bed", 1.0, 2.0, 0.9, 0.9)]).centred()
    pulls = load("seat_desk_pulls").seat_pulls(room, default_stats("bedroom"))
    lateral, forward = pulls["overlap depth"]
    assert forward > 0 and abs(lateral) < 1e-6 * forward  # out of the desk's front, where study_zone wants it
    assert pulls["overlap depth, seat-desk uncharged"] == (0.0, 0.0)
    assert pulls["out of bound x5"] == (0.0, 0.0)  # everything inside the walls


def test_seat_desk_pulls_says_where_a_seat_left_its_desk():
    went = load("seat_desk_pulls").where_the_seat_went
    desk = box("desk", 2.0, 0.35, 0.6, 0.3)  # facing +z, 1.2 m wide
    assert went(make_layout([desk, box("chair", 2.0, 0.2, 0.25, 0.25)])) == "behind the desk's centre"
    assert went(make_layout([desk, box("chair", 2.8, 0.8, 0.25, 0.25)])) == "sideways"  # 0.8 m > 0.6 + 0.1
    assert went(make_layout([desk, box("chair", 2.0, 2.0, 0.25, 0.25)])) == "too far in front"
    assert went(make_layout([desk, box("double_bed", 1.0, 2.0, 0.9, 0.9)])) == "no desk or no seat"


def test_descent_offline_caches_its_rooms_and_writes_a_run_folder_that_samples(tmp_path, capsys):
    from conftest import perturb_zero_init, write_tiny_train_config
    from agents.train import load_trained_policy

    config = write_tiny_train_config(tmp_path, algorithm="descent-imitation",
                                     ddpo={"samples_per_floor": 1, "minibatch_size": 4, "descent_steps": 20,
                                           "overlap_measure": "depth"})
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), 0).save(tmp_path / "prior.pt")  # gradients flow
    args = [str(config), "--rooms", "6", "--epochs", "1", "--batch", "4", "--other-floors", "4",
            "--cache", str(tmp_path / "rooms.pt"), "--out", str(tmp_path / "offline")]
    load("descent_offline").main(args)
    first = capsys.readouterr().out
    rooms = torch.load(tmp_path / "rooms.pt")
    assert len(rooms["x_in"]) == len(rooms["cond"]) == len(rooms["target"]) == 6
    assert rooms["target"].shape == rooms["x_in"].shape and rooms["target"].abs().max() <= 1
    assert "6 rooms in" in first and "epoch 1: loss" in first and "the prior: penalty" in first
    assert "of the move on its rooms" in first
    load("descent_offline").main(args + ["--init", str(tmp_path / "offline"), "--other-floors", "0"])
    again = capsys.readouterr().out
    assert "rooms in" not in again and "epoch 1: loss" in again  # read from the cache
    assert "other floors" not in again  # none sampled
    policy, cfg = load_trained_policy(tmp_path / "offline")
    assert cfg.algorithm == "descent-imitation"
    assert any(p.abs().sum() > 0 for n, p in policy.model.named_parameters() if "lora_B" in n)


def test_descent_probe_scores_the_adapter_and_fits_a_fresh_network_to_the_moves(tmp_path, capsys):
    from conftest import perturb_zero_init, write_tiny_train_config

    config = write_tiny_train_config(tmp_path, algorithm="descent-imitation",
                                     ddpo={"samples_per_floor": 1, "minibatch_size": 4, "descent_steps": 20,
                                           "overlap_measure": "depth"})
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), 0).save(tmp_path / "prior.pt")
    rooms, run = str(tmp_path / "rooms.pt"), str(tmp_path / "offline")
    load("descent_offline").main([str(config), "--rooms", "6", "--epochs", "1", "--batch", "4", "--other-floors",
                                  "2", "--cache", rooms, "--out", run])
    capsys.readouterr()
    load("descent_probe").main([str(config), "--cache", rooms, "--held-out", rooms, "--run", run,
                                "--epochs", "20", "--batch", "3", "--lr", "0.003"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("6 rooms to train on, 6 held out; the move's mean square")
    assert lines[1].startswith(f"the adapter of {run}: explains")
    shares = [float(line.split("explains ")[1].split("%")[0]) for line in lines[2:]]
    assert len(shares) == 20 and shares[-1] > max(shares[0], 0.0)  # it learns the moves it is shown
    from agents.train import load_train_config
    load("descent_probe").main([str(config), "--cache", rooms, "--held-out", rooms, "--run", run, "--epochs", "0",
                                "--held-out-floor-seed", str(load_train_config(config).floor_seed)])
    found = re.findall(r"the held-out rooms, (.+): Col_obj ([\d.]+)%, R_reach ([\d.]+)%", capsys.readouterr().out)
    rates = {name: (float(col), float(reach)) for name, col, reach in found}
    assert list(rates) == ["the prior", "descended", "the adapter"]
    assert all(0 <= v <= 100 for pair in rates.values() for v in pair)


def test_descent_fit_takes_the_batch_towards_its_moves_and_samples_other_floors(tmp_path, capsys):
    from conftest import perturb_zero_init, write_tiny_train_config

    config = write_tiny_train_config(tmp_path, algorithm="descent-imitation",
                                     ddpo={"samples_per_floor": 1, "minibatch_size": 4, "descent_steps": 20,
                                           "overlap_measure": "depth", "learning_rate": 0.01})
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), 0).save(tmp_path / "prior.pt")
    load("descent_fit").main([str(config), "--updates", "10", "--floors", "4"])
    lines = capsys.readouterr().out.splitlines()
    before = float(lines[0].rsplit("miss ", 1)[1])
    after = float(lines[1].split("miss ", 1)[1].split(",")[0])
    assert after < before
    assert "4 other floors, with the adapter: penalty" in lines[2] and "the prior: penalty" in lines[3]


def test_best_of_floor_metrics_picks_each_floors_cleanest_sampling(tmp_path, capsys):
    """Two samplings of two floors: floor 0 is clean in the second sampling only, floor 1 in the first only; each
    floor's best is the clean one. Floor 1's second room holds 2 ground objects, not 4: the fewest-objects pick
    takes it (and floor 0's first, the first of a tie), collisions and all."""
    def report(path, scenes):
        path.write_text(json.dumps({"per_scene": [{"ground_objects": g, "colliding": c, "unreachable_objects": u}
                                                   for g, c, u in scenes]}))
        return str(path)

    a = report(tmp_path / "a.json", [(4, [0, 1], [2]), (4, [], [])])
    b = report(tmp_path / "b.json", [(4, [], []), (2, [0, 1], [1])])
    load("best_of_floor_metrics").main([a, b])
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["2 floors, 2 samplings each",
                     "all samplings: Col_obj 28.6%, R_reach 85.7%, 3.50 ground objects per room",
                     "each floor's best: Col_obj 0.0%, R_reach 100.0%, 4.00 ground objects per room",
                     "each floor's fewest ground objects: Col_obj 66.7%, R_reach 66.7%, 3.00 ground objects per room"]
    with pytest.raises(SystemExit, match="different numbers of scenes"):
        load("best_of_floor_metrics").main([a, report(tmp_path / "c.json", [(4, [], [])])])


def test_same_objects_samplings_give_every_sampling_of_a_floor_the_same_objects(tmp_path):
    """A tiny prior (its zero-initialised layers perturbed) on 3 floors, two samplings: each floor's rooms hold the
    same objects in both, arranged differently, and the floors' rooms differ from each other."""
    from conftest import perturb_zero_init
    from iarcs_env.datasets import load_layouts, save_layouts
    from iarcs_env.datasets.procedural import generate_layouts
    from iarcs_env.env import default_stats

    torch.manual_seed(0)
    perturb_zero_init(ScenePrior.create("bedroom", default_stats("bedroom"), "tiny"), 0).save(tmp_path / "prior.pt")
    save_layouts(generate_layouts("bedroom", 3, seed=5), tmp_path / "floors.json")
    load("same_objects_samplings").main(["--room", "bedroom", "--floors", str(tmp_path / "floors.json"), "--prior",
                                         str(tmp_path / "prior.pt"), "--out", str(tmp_path / "G"), "--seeds", "0",
                                         "1", "--steps", "4"])
    a, b = (load_layouts(tmp_path / f"G_{s}.json", "bedroom") for s in (0, 1))
    assert [sorted(x.labels) for x in a] == [sorted(y.labels) for y in b]
    assert len({tuple(sorted(x.labels)) for x in a}) > 1
    assert all(len(x.labels) and not np.allclose(x.translations, y.translations) for x, y in zip(a, b))


def test_task_by_floor_and_same_floors_tell_the_floors_choice_from_the_samplings(tmp_path, capsys):
    """research/task_by_floor.py and tv_bed_facing.py --same-floors on two samplings of two floors: on the first the
    bed faces the room's length (passes) in one sampling and a wall 2 m away (fails) in the other; the second holds
    no TV stand in either."""
    import math

    from iarcs_env.datasets import save_layouts

    long = [(0, 0), (3, 0), (3, 6), (0, 6)]
    wide = [box("double_bed", 1.5, 1.0, 0.9, 1.0), box("tv_stand", 1.5, 4.0, 0.6, 0.2, yaw=math.pi)]
    narrow = [box("double_bed", 1.0, 3.0, 0.9, 1.0, yaw=math.pi / 2),
              box("tv_stand", 2.75, 3.0, 0.6, 0.2, yaw=-math.pi / 2)]
    empty = [box("double_bed", 1.5, 1.0, 0.9, 1.0)]
    for name, first in (("s0", wide), ("s1", narrow)):
        save_layouts([make_layout(first, floor=long), make_layout(empty, floor=long)], tmp_path / f"{name}.json")
    files = [str(tmp_path / "s0.json"), str(tmp_path / "s1.json")]
    load("task_by_floor").main(["tv_from_bed", *files])
    out = capsys.readouterr().out
    assert "25.0% of 4 rooms pass" in out and "  0: 1 floors" in out and "  1: 1 floors" in out
    assert "best of 2): 50.0%" in out
    load("tv_bed_facing").same_floors(files)
    out = capsys.readouterr().out
    assert "  1: 1 floors, tv_from_bed 50.0%" in out and "  2: 1 floors, tv_from_bed 0.0%" in out
    assert "tv_from_bed 100.0% where the bed faces 2.3 m or more, 0.0% where less" in out


def test_back_to_wall_measures_from_the_back_edge_along_the_objects_axis():
    """research/back_to_wall.py: a wardrobe facing into the room with its back on the wall is 0 m from it; one turned
    round, its back 0.6 m into the room, is 0.6 m away; one standing sideways along a wall is as far as the nearest
    wall on its own front-back axis (the relation's measure), not as near as the wall beside it."""
    import math

    script = load("back_to_wall")
    on_wall = box("wardrobe", 2.0, 0.3, 0.5, 0.3)                  # faces +z, back edge at z = 0
    turned = box("wardrobe", 2.0, 0.3, 0.5, 0.3, yaw=math.pi)      # faces -z, back edge at z = 0.6
    sideways = box("wardrobe", 2.5, 0.5, 0.5, 0.3, yaw=math.pi / 2)  # faces +x along the z = 0 wall, back at x = 2.2
    d = script.back_distances([make_layout([on_wall, turned, sideways, box("double_bed", 3.0, 2.0, 0.5, 0.5)])],
                              "wardrobe")
    # the sideways one: 1.8 m to the x = 4 wall, the nearest on its axis (the relation looks both ways along it),
    # though the wall beside it is 0.5 m away
    assert np.allclose(d, [0.0, 0.6, 1.8])


def test_task_descent_moves_a_tv_stand_out_to_where_the_bed_sees_it(tmp_path, capsys):
    """research/task_descent.py: a TV stand pushed into the foot of the bed, 1.1 m from its centre (tv_from_bed asks
    2-4 m), is moved out by the planner's program's gradient at the shipped adapter's last phase's weights."""
    import math

    from iarcs_env.datasets import load_layouts, save_layouts
    from iarcs_env.metrics import evaluate_layouts

    long = [(0, 0), (3, 0), (3, 6), (0, 6)]
    room = [box("double_bed", 1.5, 1.1, 0.9, 1.0), box("tv_stand", 1.5, 2.2, 0.6, 0.2, yaw=math.pi)]
    save_layouts([make_layout(room, floor=long)], tmp_path / "s.json")
    assert evaluate_layouts(load_layouts(tmp_path / "s.json", "bedroom"))["Col_obj"] == 1
    config = "experiments/ablations/task_tv_from_bed_objects_given_gradient_ranked_settle.yaml"
    load("task_descent").main(["tv_from_bed", str(HERE.parent / config), str(tmp_path / "s.json"),
                               "--out", str(tmp_path / "d.json"), "--steps", "60"])
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("before: tv_from_bed success 0.0%")
    assert out[1].startswith("after: tv_from_bed success 100.0%")
    (moved,) = load_layouts(tmp_path / "d.json", "bedroom")
    bed, stand = (moved.translations[moved.labels.index(c)] for c in ("double_bed", "tv_stand"))
    assert np.hypot(*(stand - bed)[0:3:2]) >= 2.0
    assert evaluate_layouts([moved])["Col_obj"] == 0


# --- layout_search.py ----------------------------------------------------------------------------------------------
search = load("layout_search")
SQUARE = [(0, 0), (4, 0), (4, 4), (0, 4)]


def boxed_in():
    """A double bed against the z = 0 wall with a nightstand between it and the x = 0 wall: a 0.5 m gap, where a
    wheelchair (0.9 m) does not reach the nightstand; a wardrobe on the far wall."""
    return make_layout([box("double_bed", 1.4, 1.0, 0.9, 1.0), box("nightstand", 0.25, 0.25, 0.25, 0.25),
                        box("wardrobe", 3.0, 3.7, 0.6, 0.3, yaw=np.pi)], floor=SQUARE)


def test_layout_search_frees_a_boxed_in_nightstand_with_the_rooms_own_furniture_on_the_floor_and_clear():
    from iarcs_env.metrics import batch_float64, evaluate_layouts
    from iarcs_env.tasks import task_results

    room = boxed_in()
    assert not task_results("wheelchair", [room])[0] and search.wheelchair_score(batch_float64([room]))[0] < 3
    (moved,) = search.search_room(batch_float64([room]), "wheelchair").to_layouts()
    assert task_results("wheelchair", [moved])[0]
    assert moved.labels == room.labels and np.allclose(moved.half_sizes, room.half_sizes)
    metrics = evaluate_layouts([moved])
    assert metrics["Col_obj"] == 0 and metrics["R_out"] == 0
    # what passes already stays where it is
    again = search.search_room(batch_float64([moved]), "wheelchair")
    np.testing.assert_allclose(again.to_layouts()[0].translations, moved.translations, atol=1e-9)



def test_layout_search_within_a_radius_moves_each_object_at_most_that_far_in_its_own_turn():
    from iarcs_env.metrics import batch_float64
    from iarcs_env.tasks import task_results

    start = batch_float64([boxed_in()])  # the nightstand's 0.5 m gap must widen to 0.9 m: the bed moved 0.4 m or more
    (room,) = start.to_layouts()
    for radius, passes in ((0.2, False), (0.5, True)):
        (moved,) = search.search_room(start, "wheelchair", grid=0.05, sweeps=1, radius=radius).to_layouts()
        assert task_results("wheelchair", [moved])[0] == passes
        assert np.linalg.norm((moved.translations - room.translations)[:, 0:3:2], axis=1).max() <= radius + 1e-9
        np.testing.assert_allclose(moved.yaws, room.yaws)
        assert search.wheelchair_score(batch_float64([moved]))[0] >= search.wheelchair_score(start)[0]

def test_layout_search_rooms_keeps_the_batch_and_rejects_tasks_without_a_search():
    from iarcs_env.metrics import batch_float64
    from iarcs_env.tasks import task_results

    batch = batch_float64([boxed_in(), boxed_in()])
    out = search.search_rooms(batch, "wheelchair")
    assert len(out) == 2 and torch.equal(out.labels, batch.labels) and task_results("wheelchair", out).all()
    with pytest.raises(ValueError, match="no layout search for task 'tv_from_bed'; tasks with one: wheelchair"):
        search.search_room(batch[[0]], "tv_from_bed")


def test_wheelchair_search_reports_the_rooms_before_and_after(tmp_path, capsys):
    from iarcs_env.datasets import load_layouts, save_layouts
    from iarcs_env.tasks import task_results

    save_layouts([boxed_in()], tmp_path / "s.json")
    load("wheelchair_search").main([str(tmp_path / "s.json"), "--out", str(tmp_path / "w.json")])
    assert "1 rooms: wheelchair passes 0.0% -> 100.0%" in capsys.readouterr().out
    assert task_results("wheelchair", load_layouts(tmp_path / "w.json", "bedroom")).all()


def test_search_sft_caches_searched_rooms_per_floor_seed_and_trains_on_them_together(tmp_path, capsys):
    from conftest import perturb_zero_init, write_tiny_train_config
    from agents.train import load_trained_policy

    config = write_tiny_train_config(tmp_path, algorithm="physics-gradient", adapt=["position", "yaw"])
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), 0).save(tmp_path / "prior.pt")  # gradients flow
    script = load("search_sft")
    common = [str(config), "--task", "wheelchair", "--rooms", "3", "--other-floors", "2", "--batch", "2"]
    for seed in (5, 6):
        script.main(common + ["--floor-seed", str(seed), "--cache", str(tmp_path / f"r{seed}.pt"), "--steps", "0"])
        assert torch.load(tmp_path / f"r{seed}.pt")["floor_seed"] == seed
    capsys.readouterr()
    script.main(common + ["--cache", str(tmp_path / "r5.pt"), "--cache", str(tmp_path / "r6.pt"), "--steps", "2",
                          "--eval-every", "2", "--out", str(tmp_path / "run")])
    out = capsys.readouterr().out
    assert "6 searched rooms: wheelchair" in out and "step 2: loss" in out
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    (events,) = (tmp_path / "run" / "tb").glob("events.out.tfevents.*")
    scalars = EventAccumulator(str(events)).Reload().Tags()["scalars"]
    assert {"fine_tune/loss", "fine_tune/wheelchair_held_out"} <= set(scalars)  # its time, for ship_task_adapter.py
    policy, cfg = load_trained_policy(tmp_path / "run")
    assert cfg.adapt == ["position", "yaw"]
    with pytest.raises(SystemExit, match="missing: .*r7.pt"):
        script.main(common + ["--cache", str(tmp_path / "r5.pt"), "--cache", str(tmp_path / "r7.pt")])


def test_layout_search_with_a_margin_leaves_room_to_spare():
    from iarcs_env.metrics import batch_float64
    from iarcs_env.tasks import task_results

    room = batch_float64([boxed_in()])
    plain, spare = (search.search_room(room, "wheelchair", margin=m) for m in (0.0, 0.1))
    assert task_results("wheelchair", plain)[0] and search.wheelchair_score(plain, 0.1)[0] < 3
    assert task_results("wheelchair", spare)[0] and search.wheelchair_score(spare, 0.1)[0] >= 3


def test_restore_probe_restores_handed_rooms_with_their_classes_and_reports_each_t(tmp_path, capsys):
    from conftest import write_tiny_train_config
    from iarcs_env.datasets import save_layouts

    probe = load("restore_probe")
    config = write_tiny_train_config(tmp_path, algorithm="physics-gradient", adapt=["position", "yaw"])
    save_layouts([boxed_in(), boxed_in()], tmp_path / "rooms.json")
    probe.main([str(config), str(tmp_path / "rooms.json"), "--task", "wheelchair", "--t", "0", "500", "--jitter", "0.1"])
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "2 rooms as handed: Col_obj 0.0%, wheelchair 0.0%"
    assert [line.split(":")[0] for line in out[1:]] == ["jittered by sigma = 0.1 m", "restored from t = 0",
                                                        "restored from t = 500"]
    assert "(of those passing as handed – still pass, of the others 0.0%)" in out[2]
    from agents.train import load_train_config
    from descent_offline import build_with_targets

    cfg = load_train_config(config)
    _, policy = build_with_targets(cfg)
    rooms = probe.load_rooms(str(tmp_path / "rooms.json"), policy.prior.spec, cfg, None)
    once, again = (probe.restore(policy, rooms, 250, cfg.num_steps, cfg.eta) for _ in range(2))
    assert torch.equal(once.labels, rooms.labels) and torch.equal(once.translations, again.translations)
    assert probe.ground_move(rooms, rooms) == 0 and probe.ground_move(rooms, once) > 0
    moved = probe.jitter(rooms, 0.1, torch.Generator().manual_seed(0))
    assert 0.03 < probe.ground_move(rooms, moved) < 0.3
    assert torch.equal(moved.translations[..., 1], rooms.translations[..., 1])


def test_out_of_bound_floors_writes_the_data_rooms_of_the_floors_a_sampling_put_an_object_out_of(tmp_path, capsys):
    """Two L-shaped floors; one sampling's wardrobe is through the notch of floor a: a's data room is written,
    not b's, whose sample keeps everything inside."""
    from iarcs_env.datasets import load_layouts, save_layouts

    script = load("out_of_bound_floors")
    inside = [box("wardrobe", 1.0, 1.0, 0.5, 0.5)]
    data = [make_layout(inside, floor=L_SHAPE, id=name) for name in ("a", "b")]
    samples = [make_layout([box("wardrobe", 3.0, 2.0, 0.5, 0.5)], floor=L_SHAPE, id="a:sample"),
               make_layout(inside, floor=L_SHAPE, id="b:sample")]
    assert script.out_of_bound_floors(samples) == {"a": 1}
    save_layouts(data, tmp_path / "data.json")
    save_layouts(samples, tmp_path / "s.json")
    assert script.main([str(tmp_path / "data.json"), str(tmp_path / "s.json"), "--out", str(tmp_path / "h.json")]) == 0
    assert [lay.id for lay in load_layouts(tmp_path / "h.json", num_scenes=0)] == ["a"]
    assert "1 objects out of bound on 1 floors; 1 data rooms" in capsys.readouterr().out


def test_notch_probe_conditions_on_the_bounding_rectangle_but_counts_against_the_true_floor():
    """An L-shaped floor's bounding rectangle is its 4 x 4 square; the shipped prior, told the floor is that
    square, puts over three times as many objects out of the true floor (in the notch) as when told the truth."""
    script = load("notch_probe")
    floor = make_layout([], floor=L_SHAPE).floor
    assert sorted(map(tuple, script.bounding_rectangle(floor).vertices.tolist())) == [(0, 0), (0, 4), (4, 0), (4, 4)]
    prior = ScenePrior.load_default("bedroom")
    seen, n_seen = script.out_of_true_floor(prior, [floor] * 32, [floor] * 32)
    blind, n_blind = script.out_of_true_floor(prior, [floor] * 32, [script.bounding_rectangle(floor)] * 32)
    assert blind / n_blind > 3 * seen / n_seen


def test_self_distill_keeps_only_clean_passes_and_fine_tunes_on_its_own_rooms(tmp_path, capsys):
    import dataclasses

    from conftest import perturb_zero_init, write_tiny_train_config
    from agents.train import load_train_config, load_trained_policy
    from iarcs_env.metrics import batch_float64
    from iarcs_env.tasks import task_results

    script = load("self_distill")  # puts research/ on the path
    from descent_offline import build_with_targets
    from search_sft import save_run

    (passing,) = search.search_room(batch_float64([boxed_in()]), "wheelchair").to_layouts()
    through_wall = passing.translations.copy()
    through_wall[2, 0] = passing.floor.vertices[:, 0].min()  # the wardrobe half through the wall
    outside = dataclasses.replace(passing, translations=through_wall)
    rooms = batch_float64([boxed_in(), passing, outside])
    assert task_results("wheelchair", rooms).tolist() == [False, True, True]  # the last one only R_out rejects
    assert script.clean_passes(rooms, "wheelchair").tolist() == [False, True, False]

    config = write_tiny_train_config(tmp_path, algorithm="physics-gradient", adapt=["position", "yaw"])
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), 0).save(tmp_path / "prior.pt")  # gradients flow
    cfg = load_train_config(config)
    save_run(build_with_targets(cfg)[1], cfg, str(tmp_path / "start"))
    common = [str(config), "--task", "wheelchair", "--init", str(tmp_path / "start"), "--rooms", "3", "--per-floor",
              "2", "--other-floors", "2", "--batch", "2", "--steps", "2", "--eval-every", "2"]
    script.main(common + ["--keep", "all", "--t-range", "0", "100", "--cache", str(tmp_path / "all.pt"),
                          "--out", str(tmp_path / "run")])
    assert "6 rooms kept on 3 floors" in capsys.readouterr().out
    assert torch.load(tmp_path / "all.pt")["floor_index"] == [0, 0, 1, 1, 2, 2]
    policy, cfg = load_trained_policy(tmp_path / "run")
    assert cfg.adapt == ["position", "yaw"]
    every = torch.load(tmp_path / "all.pt")
    torch.save({**every, "floor_index": [], **{k: every[k][:0] for k in script.FIELDS}}, tmp_path / "none.pt")
    with pytest.raises(SystemExit, match="no room passed wheelchair cleanly"):
        script.main(common + ["--cache", str(tmp_path / "none.pt")])


def test_joint_expert_adds_the_searched_rooms_regression_to_each_gradient_update(tmp_path, capsys):
    import yaml

    from conftest import perturb_zero_init, write_tiny_train_config
    import agents.physics_gradient as pg
    from agents.train import ADAPTERS_DIR
    from safetensors.torch import load_file

    config = write_tiny_train_config(tmp_path, algorithm="physics-gradient", adapt=["position", "yaw"], epochs=1)
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), 0).save(tmp_path / "prior.pt")  # gradients flow
    load("search_sft").main([str(config), "--task", "wheelchair", "--rooms", "3", "--other-floors", "2", "--steps", "0",
                             "--cache", str(tmp_path / "rooms.pt")])
    script, train, penalty = load("joint_expert"), pg.PhysicsGradient.train, pg.config_penalty
    adapters = {}
    for weight in (0.0, 100.0):
        out = tmp_path / f"run{weight:g}"
        (tmp_path / "joint.yaml").write_text(yaml.safe_dump({**yaml.safe_load(config.read_text()), "out": str(out)}))
        script.main([str(tmp_path / "joint.yaml"), "--cache", str(tmp_path / "rooms.pt"), "--weight", str(weight),
                     "--batch", "2"])
        adapters[weight] = load_file(next((out / ADAPTERS_DIR).rglob("adapter_model.safetensors")))
    assert "3 searched rooms regressed onto beside the gradient" in capsys.readouterr().out
    assert any(not torch.equal(adapters[0.0][k], adapters[100.0][k]) for k in adapters[0.0])
    assert (pg.PhysicsGradient.train, pg.config_penalty) == (train, penalty)  # put back after the run
    (tmp_path / "ddpo.yaml").write_text(config.read_text().replace("physics-gradient", "ddpo"))
    with pytest.raises(SystemExit, match="algorithm must be physics-gradient"):
        script.main([str(tmp_path / "ddpo.yaml"), "--cache", str(tmp_path / "rooms.pt")])


def test_restore_probe_puts_each_class_back_to_find_whose_drift_costs_the_pass():
    from iarcs_env.metrics import batch_float64

    probe = load("restore_probe")
    handed = search.search_room(batch_float64([boxed_in()]), "wheelchair")  # the bed pulled off the nightstand's wall
    restored = batch_float64([boxed_in().centred()])  # the bed drifted back: the nightstand boxed in again
    text = probe.put_back(restored, handed, "wheelchair", min_objects=1)
    parts = dict(part.split(" ", 1) for part in text.split("; "))
    assert parts == {"double_bed": "1.08 m, 100.0%", "nightstand": "0.00 m, 0.0%", "wardrobe": "0.00 m, 0.0%"}


def test_diffusion_dpo_prefers_the_searched_room_to_the_sampled_one_against_its_frozen_start(tmp_path):
    from conftest import perturb_zero_init, write_tiny_train_config
    from agents.train import load_train_config
    from descent_offline import build_with_targets
    from iarcs_env.metrics import batch_float64

    dpo = load("diffusion_dpo")
    config = write_tiny_train_config(tmp_path, algorithm="physics-gradient", adapt=["position", "yaw"])
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), 0).save(tmp_path / "prior.pt")  # gradients flow
    _, policy = build_with_targets(load_train_config(config))
    reference = copy.deepcopy(policy)
    loser = batch_float64([boxed_in()] * 4)
    winner, loser = dpo.cat([search.search_rooms(loser, "wheelchair")]), dpo.cat([loser])  # float32, as the script
    assert not torch.equal(winner.translations, loser.translations)

    def margin() -> float:  # (e(w) - e_ref(w)) - (e(l) - e_ref(l)) on fixed noise, every timestep of a grid
        prior, total = policy.prior, 0.0
        for t in range(0, prior.schedule.num_train_timesteps, 100):
            gaps = []
            for rooms in (winner, loser):
                x0, labels = rooms.encode(prior.stats), rooms.labels
                cond, weight = prior.floor_condition(rooms.floors), dpo.adapted_object_weights(policy, x0)
                steps = torch.full((len(x0),), t)
                x_t = prior.with_classes(prior.schedule.q_sample(x0, steps, torch.zeros_like(x0)), steps, labels,
                                         torch.Generator().manual_seed(0))
                with torch.no_grad():
                    gaps.append(float((dpo.per_room_square(policy, x0, x_t, steps, cond, labels, weight)
                                       - dpo.per_room_square(reference, x0, x_t, steps, cond, labels, weight)).mean()))
            total += gaps[0] - gaps[1]
        return total

    assert margin() == 0.0
    dpo.dpo_train(policy, reference, winner, loser, steps=30, lr=3e-3, beta=100.0,
                  generator=torch.Generator().manual_seed(0), every=30, report=lambda step, loss: None, batch=4)
    assert margin() < 0  # the searched room now denoised better than the sampled one, relative to the start
