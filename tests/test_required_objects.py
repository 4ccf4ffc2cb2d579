"""Objects a task needs in every room: the config entries, the class lists completed, and an adapter whose rooms are
sampled with those classes given, in sampling, in DDPO's rollouts and through save / load."""

import json

import pytest
import torch

from agents.ddpo import DDPO
from agents.policy import ADAPTED_FILE, FEATURE_GROUPS, DiffusionPolicy
from agents.train import TrainConfig
from iarcs_env.relations import class_mask
from iarcs_env.required_objects import RequiredObject, with_required
from iarcs_env.rooms import get_room
from test_ddpo import FLOORS, STEPS, make_env, perturb, tiny_prior

CLASSES = list(get_room("bedroom").classes)
EMPTY = len(CLASSES)
NEEDS = [RequiredObject(("bed",), 1, "double_bed"), RequiredObject(("nightstand",), 2, "nightstand")]


def idx(*names):
    return [CLASSES.index(n) for n in names]


def counts(labels, *names):
    return class_mask(labels, CLASSES, names).sum(1)


def test_entries_parse_with_defaults_and_bad_ones_say_what_to_write():
    assert RequiredObject.from_dict({"classes": "nightstand", "at_least": 2}, CLASSES) == NEEDS[1]
    assert RequiredObject.from_dict({"classes": ["bed"], "add": "double_bed"}, CLASSES) == NEEDS[0]
    assert RequiredObject.from_dict(NEEDS[0].to_dict(), CLASSES) == NEEDS[0]
    bad = {
        "unknown object class or group 'sofa_bed'": {"classes": "sofa_bed"},
        "say which class to add": {"classes": "bed"},
        "must be a class of this room type that bed counts": {"classes": "bed", "add": "nightstand"},
        "at_least must be a positive whole number": {"classes": "desk", "at_least": 0},
        "expected a mapping like": {"classes": "desk", "count": 2},
        "share must be a fraction of the rooms": {"classes": "desk", "share": 1.5},
    }
    for message, entry in bad.items():
        with pytest.raises(ValueError, match=message):
            RequiredObject.from_dict(entry, CLASSES, "required_objects[0]")


def test_missing_objects_fill_empty_slots_in_the_canonical_order_and_nothing_else_changes():
    rooms = torch.full((4, 12), EMPTY)
    rooms[0, :3] = torch.tensor(idx("wardrobe", "double_bed", "nightstand"))   # one nightstand short
    rooms[1, :4] = torch.tensor(idx("single_bed", "nightstand", "nightstand", "wardrobe"))  # has all
    rooms[2, :1] = torch.tensor(idx("wardrobe"))                               # bed and two nightstands short
    rooms[3] = torch.tensor(idx("wardrobe") * 12)                              # no empty slot
    out = with_required(rooms, CLASSES, NEEDS)
    assert out[0].tolist() == sorted(idx("wardrobe", "double_bed", "nightstand", "nightstand")) + [EMPTY] * 8
    assert out[1].tolist() == sorted(rooms[1].tolist())
    assert out[2].tolist() == sorted(idx("wardrobe", "double_bed", "nightstand", "nightstand")) + [EMPTY] * 8
    assert out[3].tolist() == rooms[3].tolist()


def test_a_share_fills_that_fraction_of_the_rooms_with_all_their_entries_together():
    needs = [RequiredObject(("desk",), 1, "desk", 0.3), RequiredObject(("chair",), 1, "chair", 0.3)]
    assert RequiredObject.from_dict({"classes": "desk", "share": 0.3}, CLASSES) == needs[0]
    rooms = torch.full((2000, 12), EMPTY)
    rooms[:, 0] = idx("double_bed")[0]
    out = with_required(rooms, CLASSES, needs, torch.Generator().manual_seed(0))
    desk, chair = counts(out, "desk"), counts(out, "chair")
    assert (desk == chair).all()  # one draw per room: the desk and its chair come together
    assert 0.27 < desk.float().mean() < 0.33
    again = with_required(rooms, CLASSES, needs, torch.Generator().manual_seed(0))
    assert torch.equal(out, again)
    assert (counts(out, "double_bed") == 1).all()  # nothing else changes


def test_given_classes_are_what_the_network_sees_noised_to_t_and_what_the_scenes_hold():
    prior = tiny_prior()
    classes = with_required(torch.full((64, 12), EMPTY), CLASSES, NEEDS)
    x = torch.zeros(64, 12, prior.spec.feature_dim)
    for t in (999, 500, 100, 0):  # q(x_t | classes) = N(sqrt(a_t) c, (1 - a_t) I) with c the +-1 one-hot
        given = prior.with_classes(x, torch.full((64,), t), classes, torch.Generator().manual_seed(0))
        assert torch.equal(given[..., :8], x[..., :8])
        a = float(prior.schedule.alphas_cumprod[t])
        residual = given[..., 8:] - a ** 0.5 * prior.class_features(classes, x)
        assert abs(float(residual.mean())) < 0.02 and float(residual.std()) == pytest.approx((1 - a) ** 0.5, rel=0.03), t
    scenes = prior.sample(FLOORS[:4], num_steps=STEPS, generator=torch.Generator().manual_seed(0),
                          classes=classes[:4])
    assert torch.equal(scenes.labels, classes[:4])


MANY_FLOORS = FLOORS * 4  # the untrained prior fills most slots: enough rooms with a free slot to add to


def required_policy():
    policy = DiffusionPolicy(tiny_prior(), adapter="stage1", num_steps=STEPS, adapted=("position", "yaw"))
    policy.add_adapter("task", init_from="stage1", required=NEEDS)
    return policy


def hold_needs_or_are_full(labels):
    holds = (counts(labels, "bed") >= 1) & (counts(labels, "nightstand") >= 2)
    return bool((holds | (labels != EMPTY).all(1)).all()), int(holds.sum())


def test_an_adapter_with_required_objects_adds_what_its_references_rooms_lack_and_samples_those_classes():
    policy = required_policy()
    first = policy.required_classes(MANY_FLOORS, torch.Generator().manual_seed(1))
    with policy.reference_policy():
        reference = policy.prior.sample(MANY_FLOORS, STEPS, generator=torch.Generator().manual_seed(1),
                                        eps_fn=policy.eps).labels
    added = 0
    for b in range(len(MANY_FLOORS)):  # the reference's objects are kept; what was missing is added while slots last
        kept = torch.bincount(reference[b], minlength=EMPTY + 1)
        now = torch.bincount(first[b], minlength=EMPTY + 1)
        plus = (now - kept)[:EMPTY]
        missing = max(0, 1 - int(counts(reference[b:b + 1], "bed"))) + max(0, 2 - int(counts(reference[b:b + 1], "nightstand")))
        assert (plus >= 0).all() and int(plus.sum()) == min(missing, int(kept[EMPTY]))
        assert set(torch.nonzero(plus).flatten().tolist()) <= set(idx("double_bed", "nightstand"))
        added += int(plus.sum())
    assert added >= 10
    scenes = policy.sample(MANY_FLOORS, generator=torch.Generator().manual_seed(1))
    assert torch.equal(scenes.labels, first)
    assert hold_needs_or_are_full(scenes.labels)[1] >= 3
    with pytest.raises(ValueError, match="cannot adapt them"):
        policy.add_adapter("bad", init_from="stage1", adapted=("position", "class"), required=NEEDS)


def test_rollouts_give_the_classes_and_their_log_probs_are_the_policys(tmp_path):
    policy = required_policy()
    model = DDPO(policy, make_env(num_envs=32), verbose=0, samples_per_floor=4, seed=0)
    td = model.collect_rollouts()
    labels = model._last_scene.labels
    ok, holding = hold_needs_or_are_full(labels)
    assert ok and holding >= 3
    groups = labels.reshape(8, 4, -1)  # one class list per floor plan: a group's advantages compare arrangements
    assert (groups == groups[:, :1]).all() and not (groups == groups[:1, :1]).all()
    flat = td.reshape(-1)
    again = policy.log_prob(flat["x_t"], flat["t"].reshape(-1), flat["floor"], flat["action"])
    assert torch.allclose(again, flat["sample_log_prob"], atol=1e-5)  # the ratio starts at 1
    folder = policy.save_adapter(tmp_path)
    assert json.loads((folder / ADAPTED_FILE).read_text())["required_objects"] == [n.to_dict() for n in NEEDS]
    loaded = DiffusionPolicy(tiny_prior(), adapter="scratch", num_steps=STEPS)
    loaded.load_adapter(folder, "task")
    assert loaded.required["task"] == tuple(NEEDS)
    ok, holding = hold_needs_or_are_full(loaded.sample(MANY_FLOORS, generator=torch.Generator().manual_seed(3)).labels)
    assert ok and holding >= 3


def test_slots_given_empty_follow_the_reference_in_sampling_and_in_the_recomputed_log_probs():
    """Their geometry is never scored: adapting it would only add noise to the policy gradient."""
    policy = required_policy()
    perturb(policy, "task", 0)  # a "trained" task adapter
    classes = policy.required_classes(FLOORS, torch.Generator().manual_seed(1))
    empty = classes == EMPTY
    assert empty.any() and (~empty).any()
    x = torch.randn(len(FLOORS), policy.prior.num_slots, policy.prior.spec.feature_dim,
                    generator=torch.Generator().manual_seed(2))
    t, floor = torch.full((len(FLOORS),), 300), policy.prior.floor_condition(FLOORS)
    with torch.no_grad():
        task, stage1 = policy.eps(x, t, floor, classes=classes), policy.eps(x, t, floor, adapter="stage1")
    assert torch.equal(task[empty], stage1[empty])
    moved = (task - stage1).abs()[~empty]
    assert moved[:, [0, 2, 6, 7]].min() > 0 and moved[:, [1, 3, 4, 5]].max() == 0  # position and yaw only
    with torch.no_grad():  # the clean scene the physics gradient scores holds the given classes
        assert torch.equal(policy.predict_x0(x, t, floor, classes)[..., 8:].argmax(-1), classes)
    seen = []

    def spy(x_t, t, floor_context=None, classes=None):
        seen.append(classes)
        return policy.eps(x_t, t, floor_context=floor_context, classes=classes)

    # sampling hands the policy's eps the classes (twice over under classifier-free guidance: cond and uncond)
    policy.prior.sample(FLOORS, STEPS, generator=torch.Generator().manual_seed(3), eps_fn=spy, classes=classes,
                        guidance_scale=2.0)
    assert len(seen) == STEPS and all(torch.equal(c, torch.cat([classes, classes])) for c in seen)

    model = DDPO(policy, make_env(num_envs=32), verbose=0, samples_per_floor=4, seed=0)
    flat = model.collect_rollouts().reshape(-1)
    args = flat["x_t"], flat["t"].reshape(-1), flat["floor"], flat["action"]
    assert torch.allclose(policy.log_prob(*args, flat["classes"]), flat["sample_log_prob"], atol=1e-5)
    assert (flat["classes"] == EMPTY).any()
    assert (policy.log_prob(*args) - flat["sample_log_prob"]).abs().max() > 1e-4
    flat["advantage"] = torch.ones(flat.batch_size[0], 1)
    _, info = model.policy_loss(flat)  # TorchRL's loss module reads the classes too: the ratio is 1
    assert abs(info["approx_kl"]) < 1e-6 and info["clip_fraction"] == 0


def test_a_config_checks_its_required_objects_when_read():
    entry = [{"classes": "nightstand", "at_least": 2}]
    assert TrainConfig(init_adapter="default", required_objects=entry).required() == [NEEDS[1]]
    with pytest.raises(ValueError, match="needs init_adapter"):
        TrainConfig(required_objects=entry)
    with pytest.raises(ValueError, match="adapt cannot hold class"):
        TrainConfig(init_adapter="default", required_objects=entry, adapt=["position", "class"])
    with pytest.raises(ValueError, match=r"required_objects\[0\]: dining_table names no object class of this room"):
        TrainConfig(init_adapter="default", required_objects=[{"classes": "dining_table"}])


def test_an_adapter_of_some_classes_leaves_the_other_objects_to_its_reference_and_keeps_them_when_saved(tmp_path):
    """reach_1m's adapter lowers support surfaces; without the class filter it lowered the lamps as well."""
    policy = DiffusionPolicy(tiny_prior(), adapter="stage1", num_steps=STEPS, adapted=("elevation", "height"))
    policy.add_adapter("task", init_from="stage1", required=NEEDS, adapted_classes=["bed", "nightstand"])
    perturb(policy, "task", 0)
    classes = policy.required_classes(FLOORS, torch.Generator().manual_seed(1))
    beds = class_mask(classes, CLASSES, ["bed", "nightstand"])
    others = ~beds & (classes != EMPTY)
    assert beds.any() and others.any()
    x = torch.randn(len(FLOORS), policy.prior.num_slots, policy.prior.spec.feature_dim,
                    generator=torch.Generator().manual_seed(2))
    t, floor = torch.full((len(FLOORS),), 300), policy.prior.floor_condition(FLOORS)
    with torch.no_grad():
        task, stage1 = policy.eps(x, t, floor, classes=classes), policy.eps(x, t, floor, adapter="stage1")
    assert torch.equal(task[others], stage1[others])  # the other objects: the reference's, every feature
    moved = (task - stage1).abs()[beds]
    assert moved[:, [1, 4]].min() > 0 and moved[:, [0, 2, 3, 5, 6, 7]].max() == 0  # beds: elevation and height
    folder = policy.save_adapter(tmp_path)
    assert json.loads((folder / ADAPTED_FILE).read_text())["adapted_classes"] == ["bed", "nightstand"]
    loaded = DiffusionPolicy(tiny_prior(), adapter="scratch", num_steps=STEPS)
    loaded.load_adapter(folder, "task")
    loaded.add_adapter("phase2", init_from="task", required=NEEDS)  # a second phase keeps the filter
    assert loaded.adapted_classes["task"] == loaded.adapted_classes["phase2"] == ("bed", "nightstand")
    with pytest.raises(ValueError, match="needs the classes decided elsewhere"):
        policy.add_adapter("bad", init_from="stage1", adapted=("position", "class"), adapted_classes=["bed"])
    with pytest.raises(ValueError, match="names no object class of a bedroom"):
        policy.add_adapter("bad2", init_from="stage1", required=NEEDS, adapted_classes=["dining_table"])
    with pytest.raises(ValueError, match="adapt_classes needs the classes decided elsewhere"):
        TrainConfig(init_adapter="default", adapt_classes=["support_surface"])


def test_a_stage1_adapter_of_some_classes_moves_only_the_objects_its_reference_gives_those_classes(tmp_path):
    """Without given classes, a slot's class is the reference's prediction: an adapter of beds and nightstands leaves
    every other slot (and the empty ones) to the prior; the filter is saved with it, and a config needs no required
    objects for it."""
    policy = DiffusionPolicy(tiny_prior(), adapter="stage1", num_steps=STEPS, adapted=("position", "yaw"),
                             adapted_classes=["bed", "nightstand"])
    perturb(policy, "stage1", 0)
    x = torch.randn(len(FLOORS), policy.prior.num_slots, policy.prior.spec.feature_dim,
                    generator=torch.Generator().manual_seed(2))
    t, floor = torch.full((len(FLOORS),), 100), policy.prior.floor_condition(FLOORS)
    with torch.no_grad():
        adapted = policy.eps(x, t, floor)
        with policy.base_policy():
            base = policy.eps(x, t, floor)
    predicted = policy.schedule.predict_x0(x, t, base)[..., FEATURE_GROUPS["class"]].argmax(-1)
    beds = class_mask(predicted, CLASSES, ["bed", "nightstand"])
    assert beds.any() and (~beds).any()
    assert torch.equal(adapted[~beds], base[~beds])
    assert (adapted - base).abs()[beds][:, [0, 2, 6, 7]].min() > 0  # position (x, z) and yaw move
    folder = policy.save_adapter(tmp_path)
    loaded = DiffusionPolicy(tiny_prior(), adapter="scratch", num_steps=STEPS)
    assert loaded.adapted_classes[loaded.load_adapter(folder, "stage1")] == ("bed", "nightstand")
    cfg = TrainConfig(adapt=["position", "yaw"], adapt_classes=["bed", "nightstand"])  # no required objects needed
    assert cfg.adapt_classes == ["bed", "nightstand"]
