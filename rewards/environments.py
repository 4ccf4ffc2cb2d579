"""The iARCS environments as ``gym.make`` builds them: :mod:`iarcs_env.env`'s denoising MDP with the universal
composite reward (collision, boundary, accessibility, object-count prior) handed in when no ``reward`` is given.
The environment package itself never imports the rewards; gymnasium reaches these factories through the entry
points :func:`iarcs_env.env.register_envs` names."""

from __future__ import annotations

from iarcs_env.env import DenoisingEnv, DenoisingVectorEnv, default_stats
from rewards.composite import CompositeReward


def _with_reward(kwargs: dict) -> dict:
    if kwargs.get("reward") is None:
        stats = kwargs.get("stats") or default_stats(kwargs.get("room", "bedroom"))
        kwargs = {**kwargs, "reward": CompositeReward.universal(stats)}
    return kwargs


def make_env(**kwargs) -> DenoisingEnv:
    """``gym.make("iARCS-<Room>-v0", ...)``: one scene a step."""
    return DenoisingEnv(**_with_reward(kwargs))


def make_vector_env(**kwargs) -> DenoisingVectorEnv:
    """``gym.make_vec("iARCS-<Room>-v0", num_envs=B, vectorization_mode="vector_entry_point", ...)``."""
    return DenoisingVectorEnv(**_with_reward(kwargs))
