"""DDPO on the denoising MDP with a tiny prior: the loss, learning, persistence, resuming, callbacks."""

import functools

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

import iarcs_env  # noqa: F401
from conftest import perturb_zero_init
from agents.callbacks import CheckpointCallback, EvalCallback, StopTrainingOnRewardThreshold
from agents.algorithms import get_algorithm
from agents.ddpo import DDPO, DDPOSF, gae_advantages
from agents.descent_imitation import DescentImitation
from agents.physics_gradient import PhysicsGradient, physics_penalty
from rewards.composite import CompositeReward
from rewards.sandbox import SandboxedReward
from agents.denoiser import ScenePrior
from agents.policy import DiffusionPolicy
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.env import default_stats
from iarcs_env.schedule import NoiseSchedule

STEPS = 5
FLOORS = [l.centred().floor for l in generate_layouts("bedroom", 8, seed=5)]


def tiny_prior(seed=0):
    """A tiny untrained prior with its zero-initialised (adaLN-Zero) layers perturbed, so gradients flow."""
    torch.manual_seed(seed)
    return perturb_zero_init(ScenePrior.create("bedroom", default_stats("bedroom"), "tiny"), seed)


def mean_x(scene):
    """Reward: mean x position of the objects (pushes furniture towards +x)."""
    m = scene.mask.float()
    v = (scene.translations[..., 0] * m).sum(1) / m.sum(1).clamp(min=1)
    return v, {"x": v}


def make_env(num_envs=8, reward=mean_x):
    # a fresh callable per env: a test that gives it composite-style ``weights`` must not leak them to the next
    return gym.make_vec("iARCS-Bedroom-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                        floors=FLOORS, stats=default_stats("bedroom"), reward=functools.partial(reward), num_steps=STEPS)


def make_model(algo=DDPO, seed=0, **kw):
    policy = DiffusionPolicy(tiny_prior(seed), num_steps=STEPS)
    params = {"learning_rate": 1e-3, "minibatch_size": 4, "clip_range": 0.2, "samples_per_floor": 4, "seed": seed}
    params.update(kw)
    return algo(policy, make_env(), verbose=0, **params)


def adapter_weights(model):
    return {k: v.clone() for k, v in model.policy.model.state_dict().items() if "lora_" in k}


def test_lora_targets_the_attention_projections_only():
    policy = DiffusionPolicy(tiny_prior(), num_steps=STEPS)
    names = [n for n, p in policy.model.named_parameters() if p.requires_grad]
    assert names and all("lora_" in n for n in names)
    assert {n.split(".lora_")[0].rsplit(".", 1)[-1] for n in names} == {"q_proj", "k_proj", "v_proj", "out_proj"}
    assert policy.model.peft_config["stage1"].r == 16 and policy.model.peft_config["stage1"].lora_alpha == 16


@pytest.mark.parametrize("algo", [DDPO, DDPOSF])
def test_loss_with_ratio_one(algo):
    model = make_model(algo)
    x, f = torch.randn(6, 12, 30), model.venv._floor_features[:1].repeat(6, 0)
    t = torch.full((6, 1), 800)
    f = torch.from_numpy(f)
    action, log_prob = model.policy.act(x, t, f)
    adv = torch.randn(6, 1)
    batch = TensorDict({"x_t": x, "t": t, "floor": f, "action": action, "sample_log_prob": log_prob,
                        "advantage": adv}, batch_size=[6])
    loss, info = model.policy_loss(batch)
    if algo is DDPO:  # ratio 1: loss = mean(max(-A, -A)) = -mean(A), nothing clipped
        assert loss.item() == pytest.approx(-adv.mean().item(), abs=1e-6)
        assert info["clip_fraction"] == 0 and abs(info["approx_kl"]) < 1e-6
    else:  # score function: -mean(A log pi)
        assert loss.item() == pytest.approx((-(adv[:, 0] * log_prob).mean()).item(), rel=1e-5)


def test_advantages_are_normalised_per_floor_and_clipped():
    model = make_model(adv_clip_max=1.5)
    r = torch.tensor([1.0, 2.0, 3.0, 10.0, 10.0, 10.0, 10.0, 50.0])
    floor = torch.tensor([0, 0, 0, 1, 1, 1, 1, 1])
    adv = model.compute_advantages(r, floor)
    np.testing.assert_allclose(adv[:3], [-1.2247, 0.0, 1.2247], atol=1e-4)
    assert adv[7] == pytest.approx(1.5) and adv[3] == pytest.approx(-0.5)


def test_per_term_advantages_give_every_term_its_weights_share():
    """A task term with a tiny spread next to a term with a huge one: summed, the big term decides the
    advantage; standardised per term, the 1:1 weights give both the same say."""
    model = make_model(per_floor_advantages=False)
    model.venv.reward_fn.weights = {"universal": 1.0, "task": 1.0}  # what a composite reward carries
    universal = torch.tensor([10.0, -10.0, 10.0, -10.0, 0.0, 0.0, 0.0, 0.0])
    task = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.01, 0.01, -0.01, -0.01])
    floor = torch.zeros(8, dtype=torch.long)
    summed = model.compute_advantages(universal + task, floor)
    assert summed[4] - summed[6] == pytest.approx(0.02 / (universal + task).std(unbiased=False).item(), rel=1e-3)
    model.config.per_term_advantages = True
    both = model.compute_advantages(universal + task, floor, torch.stack([universal, task], 1))
    assert both[4] - both[6] > 1.0 and both[4] > 0 > both[6]
    assert both[0] > 0 > both[1]  # the universal term still counts


def test_x0_baseline_credits_each_step_with_what_the_chain_decides_after_it():
    """r = a + b, with a already readable from step 1's x0_hat and b decided later: step 0's baseline knows
    nothing (its advantage follows r), step 1's knows a (its advantage follows b)."""
    model = make_model(x0_baseline=True, per_floor_advantages=False)
    g = torch.Generator().manual_seed(1)
    a, b, noise = (torch.randn(64, generator=g, dtype=torch.float64) for _ in range(3))
    values = torch.stack([noise, a], 1)
    adv = model.compute_advantages(a + b, torch.zeros(64, dtype=torch.long), x0_values=values)
    assert adv.shape == (64, 2)
    corr = lambda u, v: torch.corrcoef(torch.stack([u.double(), v.double()]))[0, 1]  # noqa: E731
    assert corr(adv[:, 0], a + b) > 0.97 and corr(adv[:, 1], b) > 0.97 and corr(adv[:, 1], a) < 0.2
    assert adv.std(0, unbiased=False).tolist() == pytest.approx([1.0, 1.0], abs=1e-3)


def test_x0_baseline_rollouts_score_every_steps_prediction_and_learn():
    # with eta = 0 the last step lands exactly on its x0_hat (with eta = 1, 1e-6 of noise there flips the
    # argmax ties of this untrained model's clamped class features), so its prediction scores the episode
    deterministic = DDPO(DiffusionPolicy(tiny_prior(), num_steps=STEPS, eta=0.0), make_env(), verbose=0,
                         x0_baseline=True)
    rollout = deterministic.collect_rollouts()
    assert rollout["reward_x0_hat"].shape == (8, STEPS)
    torch.testing.assert_close(rollout["reward_x0_hat"][:, -1], rollout["reward"][:, 0])
    assert not torch.allclose(rollout["reward_x0_hat"][:, 0], rollout["reward"][:, 0])
    model = make_model(x0_baseline=True)
    w0 = adapter_weights(model)
    model.learn(8 * STEPS * 2)
    assert any(not torch.equal(w0[k], w) for k, w in adapter_weights(model).items())


def test_x0_baseline_with_per_term_advantages_gives_every_term_its_weights_share():
    """Two terms decided at step 1, one with 1000 times the other's spread: each step-1 advantage follows
    the sum of the standardised terms, not the big one alone."""
    model = make_model(x0_baseline=True, per_floor_advantages=False)
    model.venv.reward_fn.weights = {"universal": 1.0, "task": 1.0}  # what a composite reward carries
    model.config.per_term_advantages = True
    g = torch.Generator().manual_seed(2)
    big, small = 1000 * torch.randn(64, generator=g), torch.randn(64, generator=g)
    late_big, late_small = 1000 * torch.randn(64, generator=g), torch.randn(64, generator=g)
    terms = torch.stack([big + late_big, small + late_small], 1)
    term_values = torch.stack([torch.zeros(64, 2), torch.stack([big, small], 1)], 1)  # (B, S=2, K=2)
    adv = model.compute_advantages(terms.sum(1), torch.zeros(64, dtype=torch.long), terms,
                                   x0_values=term_values.sum(-1), x0_terms=term_values)
    corr = lambda u, v: torch.corrcoef(torch.stack([u.double(), v.double()]))[0, 1]  # noqa: E731
    z = lambda v: (v - v.mean()) / v.std(unbiased=False)  # noqa: E731
    assert corr(adv[:, 1], z(late_big) + z(late_small)) > 0.97  # step 1: what came after it, both terms
    assert corr(adv[:, 0], z(big + late_big) + z(small + late_small)) > 0.97  # step 0: everything
    assert 0.6 < corr(adv[:, 1], late_small) < 0.8  # about 1/sqrt(2): the small term's half of the say


def test_gae_advantages_sum_each_steps_change_of_the_predicted_reward():
    """Scene 0's predicted reward goes 1 -> 2 -> 3 (the terminal reward), scene 1's stays 0: the deltas are
    (1, 1) and (0, 0); GAE(0.5) sums them back from the end (1 + 0.5 * 1, 1), then centres each step."""
    rewards, values = torch.tensor([3.0, 0.0]), torch.tensor([[1.0, 2.0], [0.0, 0.0]])
    torch.testing.assert_close(gae_advantages(rewards, values, 0.5).float(), torch.tensor([[0.75, 0.5], [-0.75, -0.5]]))
    torch.testing.assert_close(gae_advantages(rewards, values, 1.0).float(),  # r - V(x_t)
                               torch.tensor([[1.0, 0.5], [-1.0, -0.5]]))
    torch.testing.assert_close(gae_advantages(rewards, values, 0.0).float(), torch.tensor([[0.5, 0.5], [-0.5, -0.5]]))


def test_gae_lambda_zero_credits_a_step_only_with_its_own_change():
    """r = a + b with a readable from step 1's x0_hat: with lambda = 0, step 0 is credited with a (what
    happened between its state and the next) and step 1 with b alone."""
    model = make_model(x0_baseline=True, gae_lambda=0.0, per_floor_advantages=False)
    g = torch.Generator().manual_seed(1)
    a, b, noise = (torch.randn(64, generator=g, dtype=torch.float64) for _ in range(3))
    adv = model.compute_advantages(a + b, torch.zeros(64, dtype=torch.long), x0_values=torch.stack([0.01 * noise, a], 1))
    corr = lambda u, v: torch.corrcoef(torch.stack([u.double(), v.double()]))[0, 1]  # noqa: E731
    assert corr(adv[:, 0], a) > 0.99 and corr(adv[:, 1], b) > 0.99 and abs(corr(adv[:, 0], b)) < 0.3
    with pytest.raises(ValueError, match="gae_lambda .* needs x0_baseline"):
        make_model(gae_lambda=0.5)


def test_physics_penalty_is_the_overlap_volume_plus_the_out_of_bound_area_and_descends():
    """Axis-aligned boxes, where the bounds' overlap is the exact one: two overlapping boxes in an L-shaped room
    and one through its notch score what the metrics' geometry measures on the decoded scene, at the given
    weights and with footprints shrunk as asked, a pair the collision reward's contact spares is charged only
    the overlap beyond its volume, a nightstand
    lifted 0.2 m adds its gap at the floor weight, and a small step down the penalty's gradient in the model
    features lowers it, moving footprints, never heights or elevations (without a floor weight)."""
    from iarcs_env import geometry as geo
    from iarcs_env.scene import SceneBatch
    from scene_factory import L_SHAPE, box, make_layout

    stats = default_stats("bedroom")
    layout = make_layout([box("wardrobe", 1.0, 1.0, 0.5, 0.3), box("cabinet", 1.8, 1.0, 0.5, 0.3),
                          box("nightstand", 3.0, 2.0, 0.3, 0.3, y0=0.2), box("double_bed", 1.0, 3.0, 0.7, 0.9)],
                         floor=L_SHAPE)
    batch = SceneBatch.from_layouts([layout.centred()])
    x0 = batch.encode(stats).clone().requires_grad_(True)
    penalty = physics_penalty(x0, stats, batch.floors)
    scene = SceneBatch.decode(x0.detach(), stats, batch.floors)
    volume = geo.box_overlap_volumes(scene.translations, scene.half_sizes, scene.yaws, scene.ground_mask).triu(1).sum()
    outside = geo.box_out_of_floor_area(scene.translations, scene.half_sizes, scene.yaws, scene.floors, scene.mask,
                                        geo.OUT_OF_BOUND_SHRINK).sum()
    assert volume > 0.05 and outside > 0.05  # both parts are there
    assert penalty.item() == pytest.approx(float(volume + outside), rel=1e-4)
    weighted = physics_penalty(x0.detach(), stats, batch.floors, out_of_bound_weight=3.0, overlap_weight=5.0)
    assert weighted.item() == pytest.approx(float(5 * volume + 3 * outside), rel=1e-4)
    whole = geo.box_out_of_floor_area(scene.translations, scene.half_sizes, scene.yaws, scene.floors, scene.mask).sum()
    assert whole > outside  # the whole footprints stick out further than the shrunk ones
    unshrunk = physics_penalty(x0.detach(), stats, batch.floors, out_of_bound_shrink=0.0)
    assert unshrunk.item() == pytest.approx(float(volume + whole), rel=1e-4)
    spared = {"pairs": [["cabinet", "wardrobe"]], "volume": 0.01}
    touching = physics_penalty(x0.detach(), stats, batch.floors, contact=spared)
    assert touching.item() == pytest.approx(float(volume - 0.01 + outside), rel=1e-4)
    assert physics_penalty(x0.detach(), stats, batch.floors, contact={**spared, "volume": 1.0}).item() == \
        pytest.approx(float(outside), rel=1e-4)
    other = physics_penalty(x0.detach(), stats, batch.floors, contact={**spared, "pairs": [["nightstand", "bed"]]})
    assert other.item() == pytest.approx(penalty.item(), rel=1e-6)
    apart = SceneBatch.from_layouts([make_layout([box("dining_chair", 1.0, 1.0, 0.25, 0.25),
                                                  box("dining_table", 1.75, 1.0, 0.3, 0.4),  # 0.2 m from the chair
                                                  box("dining_chair", 1.0, 2.5, 0.25, 0.25)],  # 1.05 m from it
                                                 room="diningroom").centred()])
    dining, at_table = default_stats("diningroom"), {"pairs": [["seat", "table"]], "volume": 0.1}
    x_apart = apart.encode(dining).clone().requires_grad_(True)
    alone = physics_penalty(x_apart, dining, apart.floors, contact=at_table)
    drawn = physics_penalty(x_apart, dining, apart.floors, contact=at_table, contact_gap_weight=2.0)
    assert alone.item() == pytest.approx(0.0, abs=1e-6)  # nothing overlaps, nothing is out of bound
    # only the near chair (0.2 m from a 0.05 m gap): the far one is not at the table
    assert drawn.item() == pytest.approx(2 * 0.15, abs=1e-3)
    drawn.sum().backward()
    chair_x, table_x = (x_apart.grad[0, i, 0] for i in (0, 1))
    assert chair_x < 0 < table_x and x_apart.grad[0, 2, :3].abs().sum() == 0  # drawn together; the far one left
    settled = physics_penalty(x_apart.detach(), dining, apart.floors, contact=at_table, contact_gap_weight=2.0,
                              contact_gap=0.2)
    assert settled.item() == pytest.approx(0.0, abs=1e-3)  # already at the gap it is drawn to
    under = SceneBatch.from_layouts([make_layout([box("dining_chair", 1.6, 1.0, 0.25, 0.25),  # 0.4 m into the table
                                                  box("dining_table", 1.75, 1.0, 0.3, 0.4)], room="diningroom")])
    x_under = under.encode(dining).clone().requires_grad_(True)
    spared = physics_penalty(x_under, dining, under.floors, contact=at_table)
    assert spared.item() == pytest.approx(0.4 * 0.8 * 0.5 - 0.1, abs=1e-3)  # the overlap beyond the contact's
    pushed = physics_penalty(x_under, dining, under.floors, contact=at_table, contact_gap_weight=2.0)
    assert pushed.item() == pytest.approx(2 * (0.4 + 0.05), abs=1e-3)  # in place of the overlap
    pushed.sum().backward()
    assert x_under.grad[0, 0, 0] > 0 > x_under.grad[0, 1, 0]  # the chair is pushed out, back to the 0.05 m gap
    walkway = physics_penalty(x_under.detach(), dining, under.floors, contact=at_table, contact_gap_weight=2.0,
                              contact_gap_walkway=True)
    assert walkway.item() == pytest.approx(pushed.item(), rel=1e-6)  # 0.9 m behind the chair once out: drawn
    walled = SceneBatch.from_layouts([make_layout([box("dining_chair", 1.6, 1.0, 0.25, 0.25),
                                                   box("dining_table", 1.75, 1.0, 0.3, 0.4),
                                                   box("cabinet", 0.7, 1.0, 0.2, 0.5)], room="diningroom")])
    x_walled = walled.encode(dining)  # the cabinet 0.45 m behind the chair: out at the gap, 0.0 m
    assert physics_penalty(x_walled, dining, walled.floors, contact=at_table, contact_gap_weight=2.0).item() == \
        pytest.approx(2 * (0.4 + 0.05), abs=1e-3)
    assert physics_penalty(x_walled, dining, walled.floors, contact=at_table, contact_gap_weight=2.0,
                           contact_gap_walkway=True).item() == pytest.approx(0.0, abs=1e-6)  # left under its table
    depth = physics_penalty(x_under.detach(), dining, under.floors, overlap_measure="depth")
    assert depth.item() == pytest.approx(0.4 + 0.02, abs=1e-3)  # out along x, the shorter way, to a 0.02 m gap
    spared_depth = physics_penalty(x_under.detach(), dining, under.floors, overlap_measure="depth", contact=at_table)
    assert spared_depth.item() == 0  # a contact pair is charged only through contact_gap_weight
    uncharged = physics_penalty(x_under.detach(), dining, under.floors, overlap_measure="depth",
                                uncharged_pairs=[["seat", "table"]])
    assert uncharged.item() == 0  # the chair may stay under its table
    other_pair = physics_penalty(x_under.detach(), dining, under.floors, overlap_measure="depth",
                                 uncharged_pairs=[["seat", "seat"]])
    assert other_pair.item() == pytest.approx(depth.item(), rel=1e-6)
    with pytest.raises(ValueError, match="ddpo.uncharged_pairs: diningroom rooms have no .nightstand."):
        physics_penalty(x_under.detach(), dining, under.floors, uncharged_pairs=[["seat", "nightstand"]])
    with pytest.raises(ValueError, match="overlap_measure"):
        physics_penalty(x_under.detach(), dining, under.floors, overlap_measure="area")
    gap = float(geo.floor_gaps(scene.translations, scene.half_sizes, scene.ground_mask).sum())
    assert gap == pytest.approx(0.2, abs=1e-3)
    lifted = physics_penalty(x0.detach(), stats, batch.floors, floor_weight=10.0)
    assert lifted.item() == pytest.approx(float(volume + outside + 10 * gap), rel=1e-4)
    penalty.sum().backward()
    assert x0.grad[..., [0, 2]].abs().sum() > 0 and x0.grad[..., [3, 5]].abs().sum() > 0
    assert (x0.grad[..., [1, 4]] == 0).all()  # overlaps are not cleared by flattening or sinking furniture
    stepped = physics_penalty(x0.detach() - 1e-3 * x0.grad, stats, batch.floors)
    assert stepped.item() < penalty.item()


def test_physics_penalty_charges_an_object_its_narrow_path_and_opens_it():
    """``reach_weight``: the nightstand behind a cabinet, reached through a 0.51 m gap at the wall of a 3 m square
    room, is charged the weight times R_reach's agent radius less its path clearance, and a small step down the
    gradient widens the gap (the cabinet moves away from it) and lowers the charge; the reachable cabinet costs
    nothing."""
    from iarcs_env.clearance import reach_clearance
    from iarcs_env.scene import SceneBatch
    from scene_factory import box, make_layout

    stats = default_stats("bedroom")
    layout = make_layout([box("cabinet", 1.25, 1.2, 1.24, 0.3), box("nightstand", 0.3, 0.3, 0.25, 0.25)],
                         floor=[(0, 0), (3, 0), (3, 3), (0, 3)])
    batch = SceneBatch.from_layouts([layout.centred()])
    x0 = batch.encode(stats).clone().requires_grad_(True)
    plain = physics_penalty(x0.detach(), stats, batch.floors)
    charged = physics_penalty(x0, stats, batch.floors, reach_weight=3.0)
    scene = SceneBatch.decode(x0.detach(), stats, batch.floors)
    clear = reach_clearance(scene.floors, scene.translations, scene.half_sizes, scene.yaws, scene.ground_mask, 0.3)
    assert clear[0, 0] >= 0.3 and clear[0, 1] == pytest.approx(0.235, abs=1e-3)
    assert (charged - plain).item() == pytest.approx(3.0 * (0.3 - 0.235), abs=3e-3)
    charged.sum().backward()
    assert x0.grad[0, 0, 0] > 0  # the cabinet is pushed to -x, away from the gap at the wall
    stepped = physics_penalty(x0.detach() - 1e-2 * x0.grad, stats, batch.floors, reach_weight=3.0)
    assert stepped.item() < charged.item()


def test_physics_gradient_lowers_the_penalty_of_its_rollouts_and_resumes_by_name(tmp_path):
    model = make_model(PhysicsGradient, learning_rate=1e-2, gradient_steps=2)
    assert get_algorithm("physics-gradient") is PhysicsGradient
    rollout = model.collect_rollouts()
    steps = model.stochastic_steps()[-2:]
    floors = [model.venv.floors[int(i)] for i in rollout["floor_index"][:, 0]]

    def penalty():
        with torch.no_grad():
            x0 = model.policy.predict_x0(rollout["x_t"][:, steps[-1]], rollout["t"][:, steps[-1]],
                                         rollout["floor"][:, steps[-1]])
        return float(physics_penalty(x0, model.venv.stats, floors).mean())

    before = penalty()
    for _ in range(20):
        info = model.train(rollout)
    assert penalty() < 0.7 * before and info["loss"] > 0
    model.save(tmp_path / "ckpt")
    resumed = DDPO.load(tmp_path / "ckpt", DiffusionPolicy(tiny_prior(), num_steps=STEPS), make_env(), verbose=0)
    assert type(resumed) is PhysicsGradient and resumed.config.gradient_steps == 2
    with pytest.raises(ValueError, match="gradient_steps must be at least 1"):
        make_model(PhysicsGradient, gradient_steps=0)


def test_descent_imitation_moves_its_predictions_by_the_descent_of_its_rooms_and_resumes_by_name(tmp_path):
    """The move is the rollouts' final rooms' descent, in x and z only, to a lower penalty; an update takes the
    adapter's clean-scene predictions at the rollout's last states towards themselves plus that move (the final
    step's prediction is the room sampled) and changes the adapter only. An x0-predicting prior, as the shipped
    ones: with epsilon prediction the last step's x0_hat hardly depends on the network."""
    prior = tiny_prior()
    prior.schedule = NoiseSchedule(prediction_type="sample")
    params = {"learning_rate": 1e-2, "minibatch_size": 4, "samples_per_floor": 4, "descent_steps": 60,
              "num_inner_epochs": 10}
    model = DescentImitation(DiffusionPolicy(prior, num_steps=STEPS), make_env(), verbose=0, **params)
    assert get_algorithm("descent-imitation") is DescentImitation
    rollout = model.collect_rollouts()
    last = rollout[:, -1]
    floors = [model.venv.floors[int(i)] for i in last["floor_index"]]
    move, info = model.targets(last["action"], floors)
    assert info["physics_descended"] < 0.7 * info["physics"]
    largest = move.abs().amax((0, 1))
    assert largest[[0, 2]].min() > 0.01 and largest[1] == 0 and largest[3:].max() == 0

    def final_prediction():
        with torch.no_grad():
            return model.policy.predict_x0(last["x_t"], last["t"], last["floor"])

    frozen = {k: v.clone() for k, v in model.policy.model.state_dict().items() if "lora_" not in k}
    before = final_prediction()
    through = model.policy.predict_x0(last["x_t"], last["t"], last["floor"], straight_through=True)
    assert torch.allclose(through.detach(), before, atol=1e-5)  # the clipped value, the unclipped one's gradient
    stats = model.train(rollout)
    after = final_prediction()
    real = (last["action"][..., 8:].argmax(-1) != model.venv.stats.spec.empty_index)[..., None]
    missed = lambda pred: float(((pred - before - move)[..., [0, 2]] * real).square().sum())  # noqa: E731
    assert missed(after) < 0.8 * missed(before)
    assert stats["move_square"] > 0 and stats["physics_descended"] == pytest.approx(info["physics_descended"])
    assert all(torch.equal(frozen[k], v) for k, v in model.policy.model.state_dict().items() if "lora_" not in k)
    model.save(tmp_path / "ckpt")
    resumed = DDPO.load(tmp_path / "ckpt", DiffusionPolicy(tiny_prior(), num_steps=STEPS), make_env(), verbose=0)
    assert type(resumed) is DescentImitation and resumed.config.descent_steps == 60
    with pytest.raises(ValueError, match="descent_steps must be at least 1"):
        make_model(DescentImitation, descent_steps=0)


def test_best_of_floor_draws_the_mid_noise_predictions_of_each_floors_best_rollout_to_its_room():
    """Of each floor's group of rollouts the one of highest reward is picked; an update takes the adapter's clean-scene
    predictions at that rollout's states of the chosen timesteps towards the room the rollout ended in."""
    prior = tiny_prior()
    prior.schedule = NoiseSchedule(prediction_type="sample")
    model = PhysicsGradient(DiffusionPolicy(prior, num_steps=STEPS), make_env(), verbose=0, learning_rate=1e-2,
                            minibatch_size=8, samples_per_floor=4, gradient_steps=1, overlap_weight=0.0,
                            out_of_bound_weight=0.0, best_of_floor_weight=1.0, best_of_floor_t=[300, 900])
    rollout = model.collect_rollouts()
    best = model.best_of_floor(rollout)
    reward, floor = rollout["reward"][:, 0], rollout["floor_index"][:, 0]
    for group in floor.unique():
        members = floor == group
        assert best[members].sum() == 1 and reward[best & members] == reward[members].max()
    chosen = model.best_of_floor_steps()
    assert 0 < len(chosen) < STEPS and all(300 <= model.venv.timesteps[i] <= 900 for i in chosen)
    finals, weights = model.final_rooms(rollout)
    states = rollout[best][:, chosen].reshape(-1)

    def missed():
        with torch.no_grad():
            x0_hat = model.policy.predict_x0(states["x_t"], states["t"], states["floor"])
        w = weights[best].repeat_interleave(len(chosen), 0)
        return float(((x0_hat - finals[best].repeat_interleave(len(chosen), 0)).square() * w).sum() / w.sum())

    before = missed()
    for _ in range(30):
        info = model.train(rollout)
    assert missed() < 0.5 * before and info["best_of_floor_square"] > 0
    with pytest.raises(ValueError, match="best_of_floor_t .* holds none of the chain's timesteps"):
        make_model(PhysicsGradient, best_of_floor_weight=1.0, best_of_floor_t=[10, 20])


LOW_TOPS = ("def reward(scene):\n"
            "    return scene.mean_of(scene.below(scene.top_height, 0.4, scale=0.3), scene.present)\n")


def test_task_surrogate_chains_the_sandboxed_programs_gradient_through_the_decoding():
    """The sandbox's d R / d geometry, chained through SceneBatch.decode, equals autograd of the same program run
    in this process on the decoded scenes, with respect to the model features."""
    from agents.physics_gradient import task_surrogate
    from iarcs_env.scene import SceneBatch
    from rewards.scene_api import Scene

    stats = default_stats("bedroom")
    layouts = [l.centred() for l in generate_layouts("bedroom", 6, seed=2)]
    batch = SceneBatch.from_layouts(layouts)
    x0 = batch.encode(stats)
    x0 = (x0 + 0.05 * torch.randn(x0.shape, generator=torch.Generator().manual_seed(0))).requires_grad_(True)
    namespace = {"torch": torch, "math": __import__("math")}
    exec(LOW_TOPS, namespace)
    local = namespace["reward"](Scene(SceneBatch.decode(x0, stats, batch.floors, keep_graph=True)))
    (expected,) = torch.autograd.grad(local.sum(), x0)
    with SandboxedReward(LOW_TOPS) as task:
        surrogate, values, size = task_surrogate(task, x0, stats, batch.floors)
    surrogate.backward()
    torch.testing.assert_close(values, local.detach(), rtol=1e-5, atol=1e-6)
    assert expected.abs().sum() > 0.1 and size > 0
    torch.testing.assert_close(x0.grad, expected, rtol=1e-4, atol=1e-5)


def task_gradient_model(task):
    reward = CompositeReward({"task": 100.0}, rewards={"task": task})
    env = gym.make_vec("iARCS-Bedroom-v0", num_envs=8, vectorization_mode="vector_entry_point", floors=FLOORS,
                       stats=default_stats("bedroom"), reward=reward, num_steps=STEPS)
    return PhysicsGradient(DiffusionPolicy(tiny_prior(), num_steps=STEPS), env, verbose=0, learning_rate=1e-2,
                           minibatch_size=4, samples_per_floor=4, gradient_steps=2, seed=0)


def test_physics_gradient_follows_the_task_rewards_gradient(capsys):
    """With a sandboxed task term in the env's composite reward, the physics gradient raises that reward on its
    rollouts' x0_hat (weighed high: the tiny prior's rooms overlap by metres^3); without one it has no task; a
    task program without a gradient (counts here, free space in practice) is said so at the first update."""
    assert make_model(PhysicsGradient).task_reward() is None
    with SandboxedReward(LOW_TOPS) as task:
        model = task_gradient_model(task)
        assert model.task_reward() == (task, 100.0)
        rollout = model.collect_rollouts()
        first = model.train(rollout)
        for _ in range(15):
            last = model.train(rollout)
    assert last["task"] > first["task"] + 0.1 and np.isfinite(last["loss"]) and first["task_gradient"] > 0
    assert "no gradient" not in capsys.readouterr().err
    with SandboxedReward("def reward(scene):\n    return scene.count('nightstand')\n") as task:
        model = task_gradient_model(task)
        assert model.train(model.collect_rollouts())["task_gradient"] == 0
    assert "warning: the task reward has no gradient" in capsys.readouterr().err


@pytest.mark.parametrize("algo", [DDPO, DDPOSF])
def test_updates_move_the_policy_towards_high_advantage_actions(algo):
    """After a few updates on one rollout, the policy puts more probability on the chains that scored
    above average and less on the others: sum_i A_i (log pi_new - log pi_old)(a_i | s_i) > 0.""" 
    model = make_model(algo, learning_rate=3e-3, minibatch_size=8, num_inner_epochs=4)
    rollout = model.collect_rollouts()
    model.set_advantages(rollout)
    steps = model.stochastic_steps()
    assert steps.tolist() == list(range(STEPS - 1))  # the deterministic step onto x_0 is not trained
    flat = rollout[:, steps].reshape(-1)
    before = model.policy.log_prob(flat["x_t"], flat["t"], flat["floor"], flat["action"]).detach()
    torch.testing.assert_close(before, flat["sample_log_prob"])  # rollout and training log-probs agree
    stats = model.train(rollout)
    after = model.policy.log_prob(flat["x_t"], flat["t"], flat["floor"], flat["action"]).detach()
    gain = (flat["advantage"][:, 0] * (after - before)).sum()
    assert gain > 0, gain
    assert stats["grad_norm"] > 0


def test_ddpo_sf_swaps_in_through_the_same_interface():
    assert get_algorithm("ddpo") is DDPO and get_algorithm("DDPO-SF") is DDPOSF
    with pytest.raises(ValueError, match="unknown algorithm"):
        get_algorithm("ppo2")
    model = make_model(DDPOSF, learning_rate=3e-4)
    w0 = adapter_weights(model)
    model.learn(8 * STEPS * 2)
    assert model.epoch == 2 and any(not torch.equal(w0[k], v) for k, v in adapter_weights(model).items())


def test_save_load_round_trip_gives_identical_samples(tmp_path):
    model = make_model()
    model.learn(8 * STEPS * 2)
    folder = model.policy.save_adapter(tmp_path / "adapters")
    assert (folder / "adapter_config.json").exists() and (folder / "adapter_model.safetensors").exists()
    other = DiffusionPolicy(tiny_prior(), num_steps=STEPS, adapter="scratch")
    other.load_adapter(folder)
    g = lambda: torch.Generator().manual_seed(9)  # noqa: E731
    a, b = model.policy.sample(FLOORS, generator=g()), other.sample(FLOORS, generator=g())
    assert torch.equal(a.labels, b.labels) and torch.allclose(a.translations, b.translations)
    with other.base_policy():  # adapters disabled: the prior, which samples differently
        c = other.sample(FLOORS, generator=g())
    assert not torch.allclose(a.translations, c.translations)


@pytest.mark.parametrize("options", [{}, {"x0_baseline": True}, {"x0_baseline": True, "gae_lambda": 0.5}],
                         ids=["plain", "x0_baseline", "gae_lambda"])
def test_resume_after_interruption_matches_an_uninterrupted_run(tmp_path, options):
    full = make_model(**options)
    full.learn(8 * STEPS * 4)

    first = make_model(**options)
    first.learn(8 * STEPS * 2, callback=CheckpointCallback(1, tmp_path / "ckpt"))
    del first  # "killed": only the checkpoint survives
    resumed = DDPO.load(tmp_path / "ckpt", DiffusionPolicy(tiny_prior(), num_steps=STEPS), make_env(), verbose=0)
    assert resumed.epoch == 2 and resumed.num_timesteps == 8 * STEPS * 2
    resumed.learn(8 * STEPS * 4)
    w_full, w_res = adapter_weights(full), adapter_weights(resumed)
    assert w_full.keys() == w_res.keys()
    for k in w_full:
        torch.testing.assert_close(w_res[k], w_full[k])


def test_callbacks_stop_and_log_to_tensorboard(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    model = make_model()
    model.tensorboard_log = tmp_path / "tb"
    seen = []
    model.learn(8 * STEPS * 10, callback=[StopTrainingOnRewardThreshold(-1e9),
                                          EvalCallback(FLOORS[:4], eval_freq=1, n_render=4),
                                          lambda loc, m: seen.append(loc["reward_mean"])])
    assert model.epoch == 1 and len(seen) == 1  # stopped after the first epoch
    acc = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 4}).Reload()
    scalars = acc.Tags()["scalars"]
    for tag in ("rollout/reward_mean", "rollout/reward_x", "train/approx_kl", "train/clip_fraction",
                "train/learning_rate", "eval/Col_obj", "eval/R_out", "eval/mean_objects",
                "eval/mean_ground_objects"):
        assert tag in scalars, tag
    assert acc.Scalars("rollout/reward_mean")[0].value == pytest.approx(seen[0])
    assert "eval/scenes" in acc.Tags()["images"] and acc.Tags()["tensors"]  # render grid, hyper-parameters text


def test_mismatched_env_and_policy_are_clear_errors():
    policy = DiffusionPolicy(tiny_prior(), num_steps=STEPS + 1)
    with pytest.raises(ValueError, match="DDIM steps"):
        DDPO(policy, make_env(), verbose=0)
    with pytest.raises(ValueError, match="multiple of samples_per_floor"):
        DDPO(DiffusionPolicy(tiny_prior(), num_steps=STEPS), make_env(num_envs=6), samples_per_floor=4, verbose=0)
    with pytest.raises(ValueError, match="unknown DDPO hyper-parameter"):
        DDPO(DiffusionPolicy(tiny_prior(), num_steps=STEPS), make_env(), learning_rat=1, verbose=0)


def test_a_kill_during_save_leaves_a_loadable_checkpoint(tmp_path):
    model = make_model()
    model.learn(8 * STEPS)
    model.save(tmp_path / "ckpt")
    (tmp_path / "ckpt").rename(tmp_path / "ckpt.old")  # killed between the two renames of the next save
    (tmp_path / "ckpt.tmp").mkdir()  # with a half-written new one
    assert DDPO.latest_checkpoint(tmp_path / "ckpt") == tmp_path / "ckpt.old"
    resumed = DDPO.load(tmp_path / "ckpt", DiffusionPolicy(tiny_prior(), num_steps=STEPS), make_env(), verbose=0)
    assert resumed.epoch == 1
    resumed.save(tmp_path / "ckpt")  # the next save cleans up
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt"]


def test_a_placement_adapter_moves_objects_but_keeps_the_priors_classes_and_sizes(tmp_path):
    """adapt=[translation, yaw]: after training, the policy's Gaussian equals the prior's on the size and
    class features and on the slots the prior leaves empty, and differs on the objects' translation and yaw;
    the choice survives save/load and is inherited by an adapter initialised from it."""
    policy = DiffusionPolicy(tiny_prior(), num_steps=STEPS, adapted=["yaw", "translation"])
    params = {"learning_rate": 1e-2, "minibatch_size": 4, "clip_range": 0.2, "samples_per_floor": 4}
    model = DDPO(policy, make_env(), verbose=0, **params)
    model.learn(8 * STEPS * 2)
    # near-clean states whose first 4 slots are empty (class `empty`, geometry 0) and the others hold objects
    x = torch.randn(3, policy.prior.num_slots, policy.prior.spec.feature_dim, generator=torch.Generator().manual_seed(1))
    x[..., 8:] = -1.0
    x[:, :4, :8], x[:, :4, -1], x[:, 4:, 8] = 0.0, 1.0, 1.0
    t, floor = torch.full((3,), 10), policy.prior.floor_condition(FLOORS[:3])
    with torch.no_grad():
        mean, _ = policy(x, t, floor)
        with policy.base_policy():
            base, _ = policy(x, t, floor)
    diff = (mean - base).abs()
    assert torch.all(diff[:, :4] == 0)  # slots the prior leaves empty: the prior's on every feature
    assert torch.all(diff[..., 3:6] == 0) and torch.all(diff[..., 8:] == 0)  # sizes and classes: the prior's
    objects = diff[:, 4:].amax((0, 1))
    assert objects[[0, 2]].min() > 1e-6 and objects[6:8].max() > 1e-6  # floor position and yaw: adapted

    folder = policy.save_adapter(tmp_path / "adapters")
    other = DiffusionPolicy(tiny_prior(), num_steps=STEPS, adapter="scratch")
    other.load_adapter(folder)
    assert other.adapted[other.adapter] == ("position", "elevation", "yaw")
    assert torch.equal(other.reference_features(), policy.reference_features())
    g = lambda: torch.Generator().manual_seed(9)  # noqa: E731
    a, b = policy.sample(FLOORS, generator=g()), other.sample(FLOORS, generator=g())
    assert torch.equal(a.labels, b.labels) and torch.allclose(a.translations, b.translations)
    other.add_adapter("task", init_from=other.adapter)
    assert other.adapted["task"] == ("position", "elevation", "yaw")
    assert DiffusionPolicy(tiny_prior(), num_steps=STEPS, adapted=["size", "yaw", "position"]).adapted["stage1"] == \
        ("position", "footprint", "height", "yaw")
    with pytest.raises(ValueError, match="unknown feature group.*colour.*choose from position"):
        DiffusionPolicy(tiny_prior(), num_steps=STEPS, adapted=["colour"])


def perturb(policy, adapter, seed):
    """Give ``adapter`` non-zero LoRA weights, as training would (its B matrices start at 0)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in policy.model.named_parameters():
            if "lora_B" in name and f".{adapter}." in name:
                p.add_(0.3 * torch.randn(p.shape, generator=g))


def test_a_copied_adapter_keeps_the_layers_of_the_adapter_it_starts_from(tmp_path, monkeypatch):
    """An adapter trained on more layers than the default (research/descent_offline.py --lora-targets), loaded
    and copied as ``iarcs train`` does with ``init_adapter``, keeps all of them: the copy predicts what it did."""
    import agents.policy as policy_module

    other = DiffusionPolicy(tiny_prior(), num_steps=STEPS, adapter="scratch")  # the default layers
    monkeypatch.setattr(policy_module, "LORA_TARGETS", r".*\.(q_proj|k_proj|v_proj|out_proj|ff\.0|ff\.3)$")
    wide = DiffusionPolicy(tiny_prior(), num_steps=STEPS)
    perturb(wide, "stage1", 0)
    assert any(".ff." in n and "lora_B" in n for n, _ in wide.model.named_parameters())
    other.load_adapter(wide.save_adapter(tmp_path / "adapters"), name="init")
    other.add_adapter("task", init_from="init")
    x = torch.randn(3, wide.prior.num_slots, wide.prior.spec.feature_dim, generator=torch.Generator().manual_seed(2))
    t, floor = torch.full((3,), 300), wide.prior.floor_condition(FLOORS[:3])
    with torch.no_grad():
        copied, trained, prior = other.eps(x, t, floor), wide.eps(x, t, floor), other.eps(x, t, floor, adapter="scratch")
    assert torch.allclose(copied, trained, atol=1e-5) and not torch.allclose(copied, prior, atol=1e-3)


def test_a_partial_adapter_follows_the_adapter_it_starts_from_and_carries_it_when_saved(tmp_path):
    """A stage-2 adapter of some features only (here height) keeps the stage-1 adapter's prediction, not the
    prior's, on the others; saved and loaded into a policy without the stage-1 adapter it samples the same."""
    policy = DiffusionPolicy(tiny_prior(), num_steps=STEPS)
    perturb(policy, "stage1", 0)  # a "trained" stage-1 adapter of every feature
    policy.add_adapter("task", init_from="stage1", adapted=["height"])
    perturb(policy, "task", 1)  # a "trained" task adapter
    assert policy.references == {"stage1": None, "task": "stage1"} and policy.adapter == "task"
    x = torch.randn(3, policy.prior.num_slots, policy.prior.spec.feature_dim, generator=torch.Generator().manual_seed(2))
    t, floor = torch.full((3,), 300), policy.prior.floor_condition(FLOORS[:3])
    with torch.no_grad():
        task, stage1 = policy.eps(x, t, floor), policy.eps(x, t, floor, adapter="stage1")
        with policy.base_policy():
            prior = policy.eps(x, t, floor)
        with policy.reference_policy():  # what a KL penalty holds the task adapter near: stage 1
            assert torch.equal(policy.eps(x, t, floor), stage1)
    assert policy.adapter == "task"
    lora = [(n, p) for n, p in policy.model.named_parameters() if "lora_" in n]
    assert lora and all(p.requires_grad == (".task." in n) for n, p in lora)  # only the task adapter trains
    others = torch.ones(policy.prior.spec.feature_dim, dtype=torch.bool)
    others[4] = False
    assert torch.equal(task[..., others], stage1[..., others])  # every feature but height: stage 1's
    assert not torch.allclose(task[..., others], prior[..., others])  # ... and not the prior's
    assert (task[..., 4] - stage1[..., 4]).abs().max() > 1e-4  # height: the task adapter's

    folder = policy.save_adapter(tmp_path / "adapters")
    assert (folder / "reference" / "stage1" / "adapter_config.json").exists()
    other = DiffusionPolicy(tiny_prior(), num_steps=STEPS, adapter="scratch")
    assert other.load_adapter(folder) == "task" and other.references["task"] == "task_reference"
    g = lambda: torch.Generator().manual_seed(5)  # noqa: E731
    a, b = policy.sample(FLOORS, generator=g()), other.sample(FLOORS, generator=g())
    assert torch.equal(a.labels, b.labels) and torch.allclose(a.translations, b.translations)
    assert torch.allclose(a.half_sizes, b.half_sizes)

    # a second phase of the task adapter (its copy, the same features) leaves the rest to stage 1 directly
    other.add_adapter("phase2", init_from="task")
    assert other.references["phase2"] == "task_reference" and other.adapted["phase2"] == ("height",)
    c = other.sample(FLOORS, generator=g())
    assert torch.equal(a.labels, c.labels) and torch.allclose(a.half_sizes, c.half_sizes, atol=1e-6)
    other.add_adapter("wider", init_from="task", adapted=["height", "elevation"])  # other features: task's mix
    assert other.references["wider"] == "task"


@pytest.mark.parametrize("prediction_type", ["sample", "v_prediction"])
def test_the_rl_stack_takes_priors_that_predict_x0_or_v_with_slot_identity(prediction_type):
    """The GPU recipe's prior (x0 prediction, slot embeddings) under DDPO: the policy's rollout is the prior's own
    sampler while the adapter is zero, its log-probs are finite, and an update moves the policy."""
    from iarcs_env.schedule import NoiseSchedule

    torch.manual_seed(0)
    prior = perturb_zero_init(ScenePrior.create("bedroom", default_stats("bedroom"), "tiny", slot_embedding=True,
                                                schedule=NoiseSchedule(prediction_type=prediction_type)), 0)
    policy = DiffusionPolicy(prior, num_steps=STEPS)
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    a = policy.sample(FLOORS[:4], generator=g())
    b = prior.sample(FLOORS[:4], num_steps=STEPS, eta=policy.eta, generator=g())
    assert torch.equal(a.labels, b.labels) and torch.allclose(a.translations, b.translations)
    model = DDPO(policy, make_env(), verbose=0, learning_rate=1e-3, minibatch_size=4, samples_per_floor=4, seed=0)
    before = adapter_weights(model)
    model.learn(8 * STEPS)
    after = adapter_weights(model)
    assert model.epoch == 1 and any(not torch.equal(before[k], after[k]) for k in before)
    assert all(torch.isfinite(v).all() for v in after.values())


def test_narrow_passages_close_or_open_each_gap_too_narrow_to_walk_through():
    """In a 4 x 3 m room, two cabinets 0.3 m apart and 1 m from every wall: the gap is charged min(0.3 - 0.05, 0.6 -
    0.3) = 0.25 and descending it closes the gap; 0.4 m apart, 0.2, and descending opens it. A chair 0.3 m from its
    table is not charged (chairs stand close at their table); a cabinet 0.3 m from a wall is."""
    from agents.physics_gradient import narrow_passages
    from iarcs_env.scene import SceneBatch
    from scene_factory import box, make_layout

    def charged(objects, room="diningroom"):
        batch = SceneBatch.from_layouts([make_layout(objects, room=room)])
        t = batch.translations.double().requires_grad_(True)
        value = narrow_passages(t, batch.half_sizes.double(), batch.yaws.double(), batch.labels, batch.spec,
                                batch.floors, batch.ground_mask)
        value.sum().backward()
        return value.item(), t.grad[0, :, 0]

    value, grad = charged([box("cabinet", 1.5, 1.5, 0.2, 0.3), box("cabinet", 2.2, 1.5, 0.2, 0.3)])  # x 1.3..1.7, 2.0..2.4
    assert value == pytest.approx(0.25, abs=1e-6)
    assert grad[0] < 0 < grad[1]  # descending moves them together: closed
    value, grad = charged([box("cabinet", 1.5, 1.5, 0.2, 0.3), box("cabinet", 2.3, 1.5, 0.2, 0.3)])
    assert value == pytest.approx(0.2, abs=1e-6)
    assert grad[0] > 0 > grad[1]  # apart: opened to 0.6 m
    assert charged([box("dining_table", 1.5, 1.5, 0.3, 0.4), box("dining_chair", 2.2, 1.5, 0.2, 0.2)])[0] == 0.0
    value, grad = charged([box("cabinet", 0.5, 1.5, 0.2, 0.3)])  # x 0.3..0.7: 0.3 m from the west wall
    assert value == pytest.approx(0.25, abs=1e-6) and grad[0] > 0  # pushed to the wall
