"""The denoising MDP: Gymnasium API, batching, determinism, terminal reward, TorchRL wrapping."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import iarcs_env  # noqa: F401  (registers the environments)
from iarcs_env import DatasetStats
from iarcs_env.env import DenoisingVectorEnv
from conftest import L_SHAPE, make_layout

STATS = DatasetStats("bedroom", [-3.0, 0.0, -3.0, 3.0, 3.0, 3.0], [0.05, 0.05, 0.05, 2.0, 1.5, 1.5])
FLOORS = [make_layout([]).floor, make_layout([], floor=L_SHAPE).floor]


def object_count(scene):
    n = scene.mask.sum(1).float()
    return n, {"count": n, "double": 2 * n}


def make(**kw):
    kw = {"floors": FLOORS, "stats": STATS, "reward": object_count, "num_steps": 4, **kw}
    return gym.make("iARCS-Bedroom-v0", **kw)


def test_registered_for_every_room_type():
    for name in ("iARCS-Bedroom-v0", "iARCS-LivingRoom-v0", "iARCS-DiningRoom-v0"):
        assert name in gym.registry
    env = gym.make("iARCS-LivingRoom-v0", floors=FLOORS, stats=DatasetStats("livingroom", STATS.bounds_translations,
                                                                             STATS.bounds_sizes), reward=object_count)
    assert env.observation_space["x_t"].shape == (21, 8 + 25)


def test_check_env_passes():
    with pytest.warns(UserWarning, match="infinity"):  # Gaussian states and actions are unbounded
        check_env(make(render_mode="rgb_array").unwrapped)


def test_episode_pays_reward_only_at_the_end_and_reports_terms():
    env = make(render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    assert obs["t"][0] == 750 and obs["floor"].shape == (256, 4)
    rewards, done = [], False
    x = np.full((12, 30), -1.0, np.float32)
    x[:3, 8 + 12] = 1.0  # three nightstands (class 12) ...
    x[3:, 8 + 21] = 1.0  # ... and nine empty slots
    while not done:
        obs, r, done, trunc, info = env.step(x)
        rewards.append(r)
    assert rewards == [0.0, 0.0, 0.0, 3.0] and not trunc
    assert info["terms"] == {"count": 3.0, "double": 6.0}
    assert info["scene"].labels == ["nightstand"] * 3
    assert env.render().shape == (256, 256, 3)


def test_same_seed_same_episode():
    a, b = make(), make()
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=7)
    assert all(np.array_equal(oa[k], ob[k]) for k in oa)
    oc, _ = b.reset(seed=8)
    assert not np.array_equal(oa["x_t"], oc["x_t"])


def test_vector_env_moves_the_batch_as_one_array_and_autoresets():
    env = gym.make_vec("iARCS-Bedroom-v0", num_envs=6, vectorization_mode="vector_entry_point",
                       floors=FLOORS, stats=STATS, reward=object_count, num_steps=3)
    assert isinstance(env.unwrapped, DenoisingVectorEnv)
    obs, info = env.reset(seed=0, options={"floor_indices": [0, 1, 0, 1, 0, 1]})
    assert obs["x_t"].shape == (6, 12, 30) and obs["floor"].shape == (6, 256, 4)
    assert not np.array_equal(obs["floor"][0], obs["floor"][1])
    rng = np.random.default_rng(0)
    for k in range(3):
        obs, r, term, trunc, info = env.step(rng.standard_normal((6, 12, 30)).astype(np.float32))
    assert term.all() and r.shape == (6,) and info["terms"]["count"].shape == (6,)
    assert len(info["scene"]) == 6
    obs, r, term, _, _ = env.step(np.zeros((6, 12, 30), np.float32))  # next-step autoreset
    assert not term.any() and (r == 0).all() and (obs["t"] == 666).all()
    with pytest.raises(ValueError, match="actions must have shape"):
        env.step(np.zeros((5, 12, 30), np.float32))


def test_bad_arguments_are_clear():
    with pytest.raises(ValueError, match="num_steps"):
        DenoisingVectorEnv(num_steps=0, floors=FLOORS, stats=STATS, reward=object_count)
    with pytest.raises(ValueError, match="floor_indices"):
        DenoisingVectorEnv(num_envs=2, floors=FLOORS, stats=STATS, reward=object_count).reset(
            options={"floor_indices": [0, 5]})


def test_torchrl_gymenv_wraps_it():
    from torchrl.envs import GymEnv

    env = GymEnv("iARCS-Bedroom-v0", floors=FLOORS, stats=STATS, reward=object_count, num_steps=3)
    env.set_seed(0)
    td = env.reset()
    assert td["x_t"].shape == (12, 30) and td["floor"].shape == (256, 4)
    rollout = env.rollout(10, break_when_any_done=True)
    assert rollout.batch_size[0] == 3
    assert rollout["next", "done"][-1].item() and rollout["next", "reward"][:-1].abs().sum() == 0
    # the terminal reward is the object count of the last action x_0
    last = rollout["action"][-1]
    n_objects = (last[:, 8:].argmax(-1) != 21).sum().item()
    assert rollout["next", "reward"][-1].item() == n_objects


def test_defaults_use_procedural_floors_and_the_universal_composite_reward():
    env = gym.make_vec("iARCS-Bedroom-v0", num_envs=3, vectorization_mode="vector_entry_point", num_steps=2)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(2):
        _, reward, term, _, info = env.step(rng.standard_normal((3, 12, 30)).astype(np.float32))
    assert term.all()
    assert set(info["terms"]) == {"collision", "boundary", "accessibility", "object_count"}
    weights = {"collision": 1.0, "boundary": 1.0, "accessibility": 0.5, "object_count": 0.5}
    np.testing.assert_allclose(reward, sum(w * info["terms"][k] for k, w in weights.items()), rtol=1e-5)
