"""Universal rewards (rewards.universal) and the composite reward (rewards.composite)."""


import numpy as np
import pytest
import torch

import shapely_reference as ref
from iarcs_env.metrics import batch_float64, evaluate_batch
from iarcs_env.scene import SceneBatch
from iarcs_env.stats import DatasetStats
from rewards import (REWARDS, CompositeReward, accessibility_reward, boundary_reward, class_frequency_reward,
                     class_presence_reward, collision_reward, floor_contact_reward, object_count_reward,
                     object_size_reward, register_reward, required_class_reward, wall_alignment_reward)
from scene_factory import L_SHAPE, box, make_layout, random_layouts


def batch(*layouts):
    return SceneBatch.from_layouts(list(layouts))


def test_registry_names_the_four_universal_rewards():
    assert {"collision", "boundary", "accessibility", "object_count"} <= set(REWARDS)


def test_collision_reward_is_one_without_collision_and_decreases_with_overlap():
    free = make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 2.0, 1.5, 0.5, 0.3)])  # touching
    lamp = make_layout([box("double_bed", 2, 1.5, 1, 1, hy=0.5), ("pendant_lamp", (2, 0.8, 1.5), (0.3, 0.3, 0.3), 0.0)])
    scenes = [free, lamp] + [make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 2.0 - d, 1.5, 0.5, 0.3)])
                             for d in (0.1, 0.2, 0.4)]
    r = collision_reward(batch(*scenes))
    assert r.dtype == torch.float32 and r.shape == (5,)
    assert r[0].item() == 1.0 and r[1].item() == 1.0
    expected = [-d * 0.6 * 0.8 for d in (0.1, 0.2, 0.4)]  # minus the overlap volume (m^3)
    np.testing.assert_allclose(r[2:].numpy(), expected, rtol=1e-5)
    assert r[2] > r[3] > r[4]


def test_collision_contact_spares_the_datas_shallow_nightstand_bed_overlap_only():
    bed = box("double_bed", 2.0, 1.5, 1.0, 1.0, hy=0.5)  # x 1..3
    shallow = make_layout([bed, box("nightstand", 0.8, 1.0, 0.25, 0.25, hy=0.3)])  # 0.05 x 0.5 x 0.6 = 0.015 m^3
    deep = make_layout([bed, box("nightstand", 1.0, 1.0, 0.25, 0.25, hy=0.3)])  # 0.075 m^3: inside the bed
    other = make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 1.95, 1.5, 0.5, 0.3)])  # 0.024 m^3
    scenes = batch(shallow, deep, other)
    contact = {"pairs": [["nightstand", "bed"]], "volume": 0.04}
    plain = collision_reward(scenes, per_object=1.0)
    spared = collision_reward(scenes, per_object=1.0, contact=contact)
    np.testing.assert_allclose(plain.numpy(), [-0.015 - 2, -0.075 - 2, -0.024 - 2], rtol=1e-5)
    np.testing.assert_allclose(spared.numpy(), [1.0, -0.075 - 2, -0.024 - 2], rtol=1e-5)
    with pytest.raises(ValueError, match="unknown object class or group 'sofa_bed'"):
        collision_reward(scenes, contact={"pairs": [["nightstand", "sofa_bed"]], "volume": 0.04})
    with pytest.raises(ValueError, match="bedroom rooms have no 'dining_table'"):  # a class of another room type
        collision_reward(scenes, contact={"pairs": [["dining_table", "bed"]], "volume": 0.04})
    with pytest.raises(ValueError, match="expected .pairs"):
        collision_reward(scenes, contact={"pairs": [["nightstand", "bed"]]})


def test_boundary_reward_is_two_inside_and_minus_the_out_area_otherwise():
    inside = make_layout([box("nightstand", 1.0, 1.0, 0.3, 0.3)], floor=L_SHAPE)
    through = make_layout([box("wardrobe", 3.0, 2.0, 0.5, 0.5), box("cabinet", 2.0, 2.0, 0.5, 0.5)], floor=L_SHAPE)
    r = boundary_reward(batch(inside, through))
    assert r[0].item() == 2.0
    assert r[1].item() == pytest.approx(-(0.9 * 0.45 + 0.45 * 0.45), rel=1e-5)
    r0 = boundary_reward(batch(through), shrink=0.0)  # the raw footprints
    assert r0[0].item() == pytest.approx(-(1.0 * 0.5 + 0.25), rel=1e-5)


def test_per_object_penalties_count_the_offending_objects_as_the_metrics_do():
    """Three wardrobes in a row, the middle one overlapping both others: three colliding objects (Col_obj
    counts objects, not pairs); an L-shaped room with two objects through its notch: two out of bound."""
    row = make_layout([box("wardrobe", x, 1.5, 0.5, 0.3) for x in (1.0, 1.9, 2.8)])
    pair = make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 1.9, 1.5, 0.5, 0.3)])
    plain = collision_reward(batch(row, pair))
    counted = collision_reward(batch(row, pair), per_object=0.5)
    np.testing.assert_allclose((plain - counted).numpy(), [1.5, 1.0], rtol=1e-6)
    through = make_layout([box("wardrobe", 3.0, 2.0, 0.5, 0.5), box("cabinet", 2.0, 2.0, 0.5, 0.5)], floor=L_SHAPE)
    inside = make_layout([box("nightstand", 1.0, 1.0, 0.3, 0.3)], floor=L_SHAPE)
    diff = boundary_reward(batch(through, inside)) - boundary_reward(batch(through, inside), per_object=1.0)
    np.testing.assert_allclose(diff.numpy(), [2.0, 0.0])


def test_floor_contact_reward_is_one_on_the_floor_and_minus_the_gaps_beyond_the_tolerance_otherwise():
    standing = make_layout([box("double_bed", 1.0, 1.5, 0.9, 1.0, y0=0.03),
                            ("ceiling_lamp", (2, 2.4, 1.5), (0.3, 0.1, 0.3), 0.0)])
    sunk = make_layout([box("double_bed", 1.0, 1.5, 0.9, 1.0, y0=-0.15), box("nightstand", 2.4, 0.5, 0.25, 0.25)])
    lifted = make_layout([box("double_bed", 1.0, 1.5, 0.9, 1.0, y0=-0.15), box("nightstand", 2.4, 0.5, 0.25, 0.25,
                                                                                y0=0.35)])
    r = floor_contact_reward(batch(standing, sunk, lifted))
    assert r[0].item() == 1.0
    np.testing.assert_allclose(r[1:].numpy(), [-0.10, -(0.10 + 0.30)], rtol=1e-5)
    assert "floor_contact" in REWARDS


def test_wall_alignment_reward_is_one_when_aligned_and_minus_the_angles_beyond_the_tolerance_otherwise():
    deg = np.pi / 180
    aligned = make_layout([box("double_bed", 1.0, 1.5, 0.9, 1.0, yaw=93 * deg),
                           ("pendant_lamp", (2, 1.8, 1.5), (0.2, 0.2, 0.2), 30 * deg)])  # lamps do not count
    turned = make_layout([box("double_bed", 1.0, 1.5, 0.9, 1.0, yaw=25 * deg),
                          box("nightstand", 2.4, 0.5, 0.25, 0.25, yaw=-40 * deg)])
    r = wall_alignment_reward(batch(aligned, turned))
    assert r[0].item() == 1.0
    assert r[1].item() == pytest.approx(-(15 + 30) * deg, rel=1e-5)  # 25 and 40 degrees off: 15 and 30 beyond 10
    assert "wall_alignment" in REWARDS


def test_accessibility_reward_prefers_an_open_room_to_a_split_one():
    empty = make_layout([("ceiling_lamp", (2, 2.4, 1.5), (0.3, 0.1, 0.3), 0.0)])
    corner = make_layout([box("wardrobe", 3.6, 0.35, 0.35, 0.3)])
    split = make_layout([box("wardrobe", 1.5, 1.5, 0.1, 1.5, hy=1.0)])
    r = accessibility_reward(batch(empty, corner, split), cell=0.05)
    wk = ref.walkable(empty.centred(), 0.05)
    assert r[0].item() == pytest.approx(1.0 - 0.1 + 0.5 * wk["clearance"], abs=1e-5)  # coverage 1, one region
    assert r[0] > r[1] > r[2]
    parts = accessibility_reward(batch(split), cell=0.05, w_coverage=0, w_clearance=0)
    assert parts[0].item() == pytest.approx(-0.2)  # two regions


def test_accessibility_reward_charges_each_unreachable_object_as_r_reach_counts_it():
    wall = box("wardrobe", 1.5, 1.5, 0.1, 1.5, hy=1.0)  # splits the room; the agent walks the larger side
    stranded = make_layout([wall, box("nightstand", 0.5, 1.5, 0.25, 0.25)])
    reachable = make_layout([wall, box("nightstand", 3.0, 1.5, 0.25, 0.25)])
    only = dict(cell=0.05, w_coverage=0, w_regions=0, w_clearance=0, per_object=2.0)
    r = accessibility_reward(batch(stranded, reachable), **only)
    assert r.tolist() == [-2.0, 0.0]  # the nightstand on the small side, at 2 per object
    assert accessibility_reward(batch(stranded), cell=0.05, w_coverage=0, w_clearance=0)[0].item() == pytest.approx(-0.2)
    unreachable = evaluate_batch(batch(stranded, reachable)).scenes
    assert [len(s.unreachable_objects) for s in unreachable] == [1, 0]  # the metric agrees


def test_object_count_prior_kl_and_log_prob():
    train = random_layouts(40, seed=1, max_objects=6)
    stats = DatasetStats.from_layouts(train)
    same = object_count_reward(SceneBatch.from_layouts(train, num_slots=12), stats=stats)
    assert torch.allclose(same, same[0].expand_as(same)) and same[0].item() == pytest.approx(0.0, abs=1e-3)
    full = [make_layout([box("chair", 0.5 + 0.3 * k, 1.0, 0.1, 0.1) for k in range(11)])] * 8
    worse = object_count_reward(SceneBatch.from_layouts(full, num_slots=12), stats=stats)
    assert worse[0].item() < -1.0
    logp = object_count_reward(SceneBatch.from_layouts(train[:4] + full[:1], num_slots=12), stats=stats,
                               mode="log_prob")
    assert logp[4] < logp[:4].min()
    with pytest.raises(ValueError, match="statistics"):
        object_count_reward(SceneBatch.from_layouts(train[:2]))


def test_object_count_ground_only_counts_furniture_so_a_lamp_cannot_replace_a_nightstand():
    bed, stand = box("double_bed", 2.0, 1.5, 1.0, 1.0), box("nightstand", 3.3, 0.8, 0.25, 0.25)
    lamp = ("pendant_lamp", (2.0, 2.5, 1.5), (0.2, 0.2, 0.2), 0.0)
    kept, swapped = make_layout([bed, stand]), make_layout([bed, lamp])  # two objects each; one piece of furniture
    scenes = SceneBatch.from_layouts([kept, swapped], num_slots=6)
    two = [0.0, 0.1, 0.9]  # training rooms: mostly two objects (or two pieces of furniture)
    every = object_count_reward(scenes, count_distribution=two, mode="log_prob")
    assert every[0] == every[1]  # counting every object, the swap is free
    furniture = object_count_reward(scenes, count_distribution=two, mode="log_prob", ground_only=True)
    assert furniture[0].item() == pytest.approx(np.log(0.9), abs=1e-3)
    assert furniture[1] < furniture[0] - 2.0  # log(0.1 / 0.9)
    with pytest.raises(ValueError, match="ground_only needs count_distribution"):
        object_count_reward(scenes, stats=DatasetStats.from_layouts([kept]), ground_only=True)


def test_class_presence_prior_is_the_bernoulli_log_likelihood_of_the_classes_present():
    bed, stand = box("double_bed", 0.0, 0.0, 1.0, 1.1), box("nightstand", 1.4, -0.8, 0.25, 0.25)
    train = [make_layout([bed, stand])] * 3 + [make_layout([stand])]
    stats = DatasetStats.from_layouts(train)
    assert stats.class_presence["double_bed"] == 0.75 and stats.class_presence["nightstand"] == 1.0
    assert DatasetStats.from_json(stats.to_json()).class_presence == stats.class_presence
    scenes = SceneBatch.from_layouts([make_layout([bed, stand]), make_layout([stand]), make_layout([bed])],
                                     num_slots=12)
    r = class_presence_reward(scenes, stats=stats, eps=1e-3)
    absent = sum(np.log(1 - 1e-3) for c, p in stats.class_presence.items() if p == 0)  # every other class
    expected = [np.log(0.75) + np.log(1 - 1e-3), np.log(0.25) + np.log(1 - 1e-3), np.log(0.75) + np.log(1e-3)]
    np.testing.assert_allclose(r.numpy(), np.array(expected) + absent, rtol=1e-5)
    assert r[0] > r[1] > r[2]  # dropping the bed costs log(0.75 / 0.25); dropping the nightstand far more
    own = class_presence_reward(scenes, class_presence={"double_bed": 0.5})
    assert own[0] == pytest.approx(own[1].item(), abs=1e-5)  # bed 50/50, nightstand unknown = rare
    # absence mode: only the missing classes' log(1 - p); a present class, however rare, costs nothing
    gone = class_presence_reward(scenes, stats=stats, eps=1e-3, mode="absence")
    np.testing.assert_allclose(gone.numpy(), np.array([0.0, np.log(0.25), np.log(1e-3)]) + absent,
                               rtol=1e-5, atol=1e-5)
    with_rare = make_layout([bed, stand, box("tv_stand", -1.5, 0.0, 0.6, 0.2)])  # a class no training room has
    assert class_presence_reward(SceneBatch.from_layouts([with_rare], num_slots=12), stats=stats,
                                 mode="absence")[0] == pytest.approx(gone[0].item() - np.log(1 - 1e-3), abs=1e-5)
    with pytest.raises(ValueError, match="class_presence"):
        class_presence_reward(scenes, stats=DatasetStats("bedroom", [0] * 6, [0] * 6))
    with pytest.raises(ValueError, match="sofa_bed"):
        class_presence_reward(scenes, class_presence={"sofa_bed": 0.5})


def test_match_modes_score_the_batch_against_the_training_rates():
    bed, stand = box("double_bed", 0.0, 0.0, 1.0, 1.1), box("nightstand", 1.4, -0.8, 0.25, 0.25)
    with_bed, without = make_layout([bed, stand]), make_layout([stand])
    stats = DatasetStats.from_layouts([with_bed] * 3 + [without])  # beds in 75% of the rooms
    # a batch at the training rate: every term is 0 (nothing to correct)
    at_rate = class_presence_reward(SceneBatch.from_layouts([with_bed] * 3 + [without], num_slots=12), stats=stats,
                                    mode="match")
    np.testing.assert_allclose(at_rate.numpy(), 0.0, atol=1e-5)
    # beds in 1 of 4 scenes (q = 0.25 < p = 0.75): the scene with the bed gains log(0.75 / 0.25), the others
    # score the absence of a bed at log(0.25 / 0.75): with p above q, having the class is what is rewarded
    few = class_presence_reward(SceneBatch.from_layouts([with_bed] + [without] * 3, num_slots=12), stats=stats,
                                mode="match")
    np.testing.assert_allclose(few.numpy(), [np.log(0.75 / 0.25)] + [np.log(0.25 / 0.75)] * 3, rtol=1e-4)
    # beds in every scene (q = 1, clipped): having one costs what an over-represented class should
    many = class_presence_reward(SceneBatch.from_layouts([with_bed] * 4, num_slots=12), stats=stats, mode="match")
    assert (many < 0).all()
    # its batch mean is minus the Bernoulli KL of the batch's rates to the training rates
    q, p = 0.25, 0.75
    kl = q * np.log(q / p) + (1 - q) * np.log((1 - q) / (1 - p))
    assert few.mean().item() == pytest.approx(-kl, rel=1e-4)
    with pytest.raises(ValueError, match="mode"):
        class_presence_reward(SceneBatch.from_layouts([with_bed]), stats=stats, mode="kl")

    # object counts: a scene with a count the batch over-represents scores below one it under-represents
    train = random_layouts(40, seed=1, max_objects=6)
    count_stats = DatasetStats.from_layouts(train)
    same = object_count_reward(SceneBatch.from_layouts(train, num_slots=12), stats=count_stats, mode="match")
    np.testing.assert_allclose(same.numpy(), 0.0, atol=0.02)  # the training set itself (up to eps)
    # 6 objects: 22.5% of the training rooms, 1 in 8 of the batch; 1 object: 5% of them, 7 in 8 of the batch
    skewed = [lay for lay in train if len(lay) == 6][:1] + [lay for lay in train if len(lay) == 1][:1] * 7
    r = object_count_reward(SceneBatch.from_layouts(skewed, num_slots=12), stats=count_stats, mode="match")
    assert r[0].item() == pytest.approx(np.log(0.225 / 0.125), abs=0.01)
    assert r[1].item() == pytest.approx(np.log(0.05 / 0.875), abs=0.01) and torch.allclose(r[1:], r[1].expand(7))


def test_required_class_prices_a_room_without_any_object_of_the_group():
    stand = box("nightstand", 1.4, -0.8, 0.25, 0.25)
    double, single = box("double_bed", 0.0, 0.0, 1.0, 1.1), box("single_bed", 0.0, 0.0, 0.5, 1.0)
    rooms = [make_layout([double, stand]), make_layout([single]), make_layout([stand]), make_layout([])]
    scenes = SceneBatch.from_layouts(rooms, num_slots=12)
    # any bed counts (the "bed" group): double and single beds pass, the room with only a nightstand and the
    # empty room pay -1
    np.testing.assert_array_equal(required_class_reward(scenes).numpy(), [0.0, 0.0, -1.0, -1.0])
    np.testing.assert_array_equal(required_class_reward(scenes, classes=["nightstand"]).numpy(), [0, -1, 0, -1])
    np.testing.assert_array_equal(required_class_reward(scenes, classes="double_bed").numpy(), [0, -1, -1, -1])
    total, terms = CompositeReward.from_config({"required_class": {"weight": 5.0, "classes": "bed"}})(scenes)
    np.testing.assert_array_equal(total.numpy(), [0.0, 0.0, -5.0, -5.0])
    # an unknown class, a typo in a list, a class bedrooms do not have
    for bad in ("sofa_bed", ["double_bed", "water_bed"], "dining_table"):
        with pytest.raises(ValueError, match="required_class"):
            required_class_reward(scenes, classes=bad)


def test_class_frequency_scores_each_object_against_the_batch_and_training_shares():
    bed, stand = box("double_bed", 0.0, 0.0, 1.0, 1.1), box("nightstand", 1.4, -0.8, 0.25, 0.25)
    lamp = ("pendant_lamp", (0.0, 2.4, 0.0), (0.2, 0.1, 0.2), 0.0)
    shares = {"double_bed": 0.25, "nightstand": 0.5, "pendant_lamp": 0.25}
    eps = 1e-9
    # the batch has the training shares: every score is 0
    at_rate = [make_layout([bed, stand, stand, lamp])] * 2
    np.testing.assert_allclose(class_frequency_reward(SceneBatch.from_layouts(at_rate, num_slots=12),
                                                      class_frequencies=shares, eps=eps).numpy(), 0.0, atol=1e-6)
    # lamps fill the rooms (3 of 6 objects): a room with a second lamp scores below one with a bed
    lamps = [make_layout([stand, lamp, lamp]), make_layout([bed, stand, lamp])]
    r = class_frequency_reward(SceneBatch.from_layouts(lamps, num_slots=12), class_frequencies=shares, eps=eps)
    g = {"double_bed": 1 / 6, "nightstand": 2 / 6, "pendant_lamp": 3 / 6}
    score = {c: np.log(shares[c] / g[c]) for c in shares}
    np.testing.assert_allclose(r.numpy(), [score["nightstand"] + 2 * score["pendant_lamp"],
                                           score["double_bed"] + score["nightstand"] + score["pendant_lamp"]],
                               rtol=1e-5)
    assert r[1] > 0 > r[0]
    # the batch sum is N times minus the KL of the batch's shares to the training shares
    kl = sum(g[c] * np.log(g[c] / shares[c]) for c in shares)
    assert r.sum().item() == pytest.approx(-6 * kl, rel=1e-5)
    with pytest.raises(ValueError, match="class_frequencies"):
        class_frequency_reward(SceneBatch.from_layouts(lamps), class_frequencies={"sofa_bed": 1.0})


def _bed(log_half_size: float, x: float = 0.0):
    h = float(np.exp(log_half_size))
    return ("double_bed", (x, h, 0.0), (h, h, h), 0.0)


def test_object_size_scores_each_object_against_the_training_and_batch_sizes():
    sizes = {"double_bed": {"log_mean": [0.0] * 3, "log_std": [0.1] * 3}}
    stand = box("nightstand", 1.5, 1.0, 0.25, 0.25)  # a class without training sizes: scores 0
    # beds at the training mean and spread (log half-sizes +-0.1): every score is 0
    typical = batch(make_layout([_bed(0.1), stand]), make_layout([_bed(-0.1)]))
    np.testing.assert_allclose(object_size_reward(typical, class_sizes=sizes).numpy(), 0.0, atol=1e-5)
    # shrunk beds (-0.1, -0.3; the batch's mean -0.2, spread 0.1): per axis, z^2 / 2 under the batch minus z^2 / 2
    # under the training sizes, 0 for the bed 1 training deviation small, 1/2 - 9/2 for the one 3 deviations
    # small; over 3 axes, centred on the class's mean (-6): +6 and -6
    shrunk = batch(make_layout([_bed(-0.1), stand]), make_layout([_bed(-0.3)]))
    np.testing.assert_allclose(object_size_reward(shrunk, class_sizes=sizes).numpy(), [6.0, -6.0], atol=1e-4)
    # deviations count up to max_z: z = -3 counts as -2 (3 x (1/2 - 2) = -4.5)
    np.testing.assert_allclose(object_size_reward(shrunk, class_sizes=sizes, max_z=2.0).numpy(), [2.25, -2.25],
                               atol=1e-4)
    # centred per class, the score does not pay for having fewer objects: its batch sum is 0
    assert object_size_reward(shrunk, class_sizes=sizes).sum().item() == pytest.approx(0.0, abs=1e-4)
    # a class with one object in the batch scores 0 (no batch spread to compare with)
    assert object_size_reward(batch(make_layout([_bed(-0.5)])), class_sizes=sizes).item() == 0.0
    with pytest.raises(ValueError, match="DatasetStats.from_layouts"):
        object_size_reward(shrunk, stats=DatasetStats.from_json(
            {"bounds_translations": [0] * 6, "bounds_sizes": [0] * 6}, "bedroom"))
    with pytest.raises(ValueError, match="sofa_bed"):
        object_size_reward(shrunk, class_sizes={"sofa_bed": sizes["double_bed"]})


def test_statistics_hold_each_class_size_distribution_and_keep_it_through_json():
    layouts = [make_layout([_bed(v, x=0.0), box("nightstand", 1.5, 1.0, 0.25, 0.25)]) for v in (0.1, 0.3)]
    stats = DatasetStats.from_layouts(layouts)
    np.testing.assert_allclose(stats.class_sizes["double_bed"]["log_mean"], [0.2] * 3)
    np.testing.assert_allclose(stats.class_sizes["double_bed"]["log_std"], [0.1] * 3)
    np.testing.assert_allclose(stats.class_sizes["nightstand"]["log_mean"], np.log([0.25, 0.4, 0.25]))
    assert DatasetStats.from_json(stats.to_json()).class_sizes == stats.class_sizes
    # the shipped priors' statistics were given their training rooms' sizes (experiments/add_class_sizes.py)
    from iarcs_env.env import default_stats
    assert default_stats("bedroom").class_sizes["double_bed"]["log_std"][2] == pytest.approx(0.0285, abs=1e-3)


@pytest.mark.parametrize("seed", [0, 1])
def test_rewards_agree_with_the_shapely_reference(seed):
    layouts = random_layouts(16, seed=seed)
    b = batch_float64(layouts)
    centred = [lay.centred() for lay in layouts]
    np.testing.assert_allclose(collision_reward(b).numpy(), [ref.collision_reward(l) for l in centred],
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(boundary_reward(b).numpy(), [ref.boundary_reward(l) for l in centred],
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(accessibility_reward(b).numpy(), [ref.accessibility_reward(l) for l in centred],
                               rtol=1e-5, atol=1e-5)


def test_composite_is_the_weighted_sum_of_its_terms():
    layouts = random_layouts(6, seed=2)
    stats = DatasetStats.from_layouts(layouts)
    b = SceneBatch.from_layouts(layouts)
    weights = {"collision": 1.0, "boundary": 0.5, "accessibility": 2.0, "object_count": 0.25}
    reward = CompositeReward(weights, stats=stats, accessibility={"cell": 0.1})
    total, terms = reward(b)
    assert set(terms) == set(weights) and total.shape == (6,)
    expected = sum(weights[k] * terms[k] for k in weights)
    assert torch.allclose(total, expected)
    assert torch.allclose(terms["collision"], collision_reward(b))
    assert reward.options["object_count"] == {"stats": stats} and "stats" not in reward.options["collision"]
    # the same from a config dict
    cfg = {"collision": 1.0, "boundary": 0.5, "accessibility": {"weight": 2.0, "cell": 0.1}, "object_count": 0.25}
    total2, _ = CompositeReward.from_config(cfg, stats=stats)(b)
    assert torch.allclose(total, total2)
    total3, _ = CompositeReward.from_config({"weights": weights, "options": {"accessibility": {"cell": 0.1}}},
                                            stats=stats)(b)
    assert torch.allclose(total, total3)


def test_composite_errors_and_custom_terms():
    with pytest.raises(ValueError, match="unknown reward"):
        CompositeReward({"no_such_reward": 1.0})
    with pytest.raises(ValueError, match="no option"):
        CompositeReward({"collision": 1.0}, collision={"cell": 0.1})

    @register_reward("test_object_count_plain")
    def plain(batch):
        return batch.mask.sum(1).float()

    b = SceneBatch.from_layouts(random_layouts(3, seed=4))
    total, terms = CompositeReward({"test_object_count_plain": 2.0, "collision": 1.0})(b)
    assert torch.allclose(total, 2 * b.mask.sum(1).float() + collision_reward(b))
    del REWARDS["test_object_count_plain"]
