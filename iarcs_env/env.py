"""The denoising chain as a Gymnasium MDP (iARCS / DDPO).

State ``s_k = (x_t, t, floor)`` with x_t the noisy scene features (N, 8 + K) at the k-th timestep t of a
DDIM grid of ``num_steps`` steps, and ``floor`` the floor condition (256 boundary points with inward
normals). The action is the next state ``x_{t-1}``; the policy is the diffusion model's DDIM Gaussian
(``agents``). The reward is 0 until the last step; at ``t = 0`` the decoded scene x_0 gets the terminal
reward ``R(x_0, floor)`` of a pluggable reward callable (default: the universal composite), and the
episode terminates. All randomness (floor plans, x_T) comes from ``np_random``.

:class:`DenoisingVectorEnv` is natively batched: one ``step`` moves B scenes as one array (use it through
``gym.make_vec(..., vectorization_mode="vector_entry_point")``); :class:`DenoisingEnv` is the one-scene
view that ``gym.make`` returns.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from .floorplan import FloorPlan
from .rooms import get_room
from .scene import SceneBatch, floor_features
from .schedule import ddim_timesteps
from .stats import DatasetStats

#: A reward maps a decoded scene batch to per-scene totals (B,), optionally with named terms.
RewardFn = Callable[[SceneBatch], "torch.Tensor | tuple[torch.Tensor, dict[str, torch.Tensor]]"]
NUM_FLOOR_POINTS = 256


def evaluate_reward(reward: RewardFn, scene: SceneBatch) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Call a reward and normalise its result to ``(total (B,), {term: (B,)})`` as float64 arrays."""
    out = reward(scene)
    total, terms = out if isinstance(out, tuple) else (out, {})
    as_np = lambda v: np.asarray(torch.as_tensor(v).detach().cpu().double().numpy(), dtype=np.float64).reshape(-1)  # noqa: E731
    return as_np(total), {k: as_np(v) for k, v in terms.items()}


STATS_DIR = Path(__file__).parent / "data" / "stats"


@lru_cache(maxsize=None)
def default_stats(room: str) -> DatasetStats:
    """The feature scaling of the shipped prior for ``room`` (``iarcs_env/data/stats/<room>.json``),
    or, for a room with no shipped prior, the statistics of 2000 procedural rooms (seed 0)."""
    room = get_room(room).name
    path = STATS_DIR / f"{room}.json"
    if path.exists():
        return DatasetStats.load(path)
    from .datasets.procedural import generate_layouts

    return DatasetStats.from_layouts(generate_layouts(room, 2000, seed=0), room)


def default_floors(room: str, count: int = 512, seed: int = 12345) -> list[FloorPlan]:
    """Floor plans of procedural rooms held out from the prior's training seeds."""
    from .datasets.procedural import generate_layouts

    return [lay.centred().floor for lay in generate_layouts(room, count, seed=seed)]


class DenoisingVectorEnv(VectorEnv):
    """B scenes denoised together: observations and actions carry a leading batch dimension B.

    Args:
        num_envs: B, the scenes moved by one step.
        room: bedroom, livingroom or diningroom.
        num_steps: DDIM steps per episode (the paper uses 20; T = 1000 training timesteps).
        floors: floor plans to draw from (any frame: they are centred), default procedural held-out rooms.
        stats: dataset statistics that scale the features; default those of the shipped prior.
        reward: terminal reward callable on a :class:`SceneBatch` (required; ``gym.make`` hands in the universal
            composite through :mod:`rewards.environments`, so this package never imports the rewards).
        num_train_timesteps: T of the noise schedule.
    """

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, room: str = "bedroom", num_steps: int = 20,
                 floors: Sequence[FloorPlan] | None = None, stats: DatasetStats | None = None,
                 reward: RewardFn | None = None, num_train_timesteps: int = 1000,
                 render_mode: str | None = None):
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.spec_room = get_room(room)
        self.num_envs = num_envs
        self.num_steps = num_steps
        self.render_mode = render_mode
        self.stats = stats or default_stats(self.spec_room.name)
        if reward is None:
            raise ValueError("the environment needs a reward: gym.make('iARCS-...-v0') hands in the universal "
                             "composite; pass reward=... (any callable SceneBatch -> (B,)) when building it directly")
        self.reward_fn = reward
        floors = list(floors) if floors is not None else default_floors(self.spec_room.name)
        if not floors:
            raise ValueError("the environment needs at least one floor plan")
        self.floors = [f.translated(-f.centre) for f in floors]
        self._floor_features = floor_features(self.floors, self.stats, NUM_FLOOR_POINTS).numpy()
        self.timesteps = ddim_timesteps(num_steps, num_train_timesteps).numpy()

        n, f = self.spec_room.max_objects, self.spec_room.feature_dim
        one = spaces.Dict({
            "x_t": spaces.Box(-np.inf, np.inf, (n, f), np.float32),
            "t": spaces.Box(0, num_train_timesteps - 1, (1,), np.int64),
            "floor": spaces.Box(-np.inf, np.inf, (NUM_FLOOR_POINTS, 4), np.float32),
        })
        self.single_observation_space = one
        self.single_action_space = spaces.Box(-np.inf, np.inf, (n, f), np.float32)
        self.observation_space = gym.vector.utils.batch_space(one, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self._k = 0
        self._x = np.zeros((num_envs, n, f), np.float32)
        self._floor_idx = np.zeros(num_envs, np.int64)
        self._needs_reset = True
        self.last_scene: SceneBatch | None = None

    # --- MDP ----------------------------------------------------------------------------------------
    def _obs(self) -> dict[str, np.ndarray]:
        t = np.full((self.num_envs, 1), self.timesteps[min(self._k, self.num_steps - 1)], np.int64)
        return {"x_t": self._x.copy(), "t": t, "floor": self._floor_features[self._floor_idx].copy()}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Draw B floor plans (``options={"floor_indices": [...]}`` picks them) and x_T ~ N(0, I)."""
        super().reset(seed=seed)
        if options and "floor_indices" in options:
            idx = np.asarray(options["floor_indices"], np.int64).reshape(-1)
            if len(idx) != self.num_envs or idx.min() < 0 or idx.max() >= len(self.floors):
                raise ValueError(f"floor_indices must be {self.num_envs} indices in 0..{len(self.floors) - 1}")
            self._floor_idx = idx
        else:
            self._floor_idx = self.np_random.integers(0, len(self.floors), self.num_envs)
        self._x = self.np_random.standard_normal(self._x.shape).astype(np.float32)
        self._k = 0
        self._needs_reset = False
        self.last_scene = None
        return self._obs(), {"floor_index": self._floor_idx.copy(), "timestep": self.timesteps[0]}

    def step(self, actions):
        """Take x_{t-1} for every scene; at the last step decode x_0 and pay the terminal reward."""
        if self._needs_reset:  # NEXT_STEP autoreset: the step after a terminal one starts new episodes
            obs, info = self.reset()
            zeros = np.zeros(self.num_envs)
            return obs, zeros, np.zeros(self.num_envs, bool), np.zeros(self.num_envs, bool), info
        x = np.asarray(actions, dtype=np.float32)
        if x.shape != self._x.shape:
            raise ValueError(f"actions must have shape {self._x.shape} (B, N, 8 + K); got {x.shape}")
        self._x = x
        self._k += 1
        reward = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, bool)
        info: dict[str, Any] = {"timestep": self.timesteps[min(self._k, self.num_steps - 1)]}
        if self._k == self.num_steps:
            scene = self.decode()
            reward, terms = evaluate_reward(self.reward_fn, scene)
            terminated[:] = True
            self.last_scene = scene
            self._needs_reset = True
            info.update({"terms": terms, "scene": scene, "timestep": 0})
        return self._obs(), reward, terminated, np.zeros(self.num_envs, bool), info

    def decode(self, x: np.ndarray | None = None) -> SceneBatch:
        """The scenes that features ``x`` (default: the current state) describe."""
        x = self._x if x is None else x
        floors = [self.floors[i] for i in self._floor_idx]
        return SceneBatch.decode(torch.from_numpy(np.asarray(x, np.float32)), self.stats, floors,
                                 ids=[f"floor_{i}" for i in self._floor_idx])

    def render(self):
        """Top-down images of the current scenes (the decoded x_t), one per scene."""
        if self.render_mode != "rgb_array":
            return None
        from .render import render_layout

        return tuple(render_layout(lay) for lay in self.decode().to_layouts())


class DenoisingEnv(gym.Env):
    """One scene of :class:`DenoisingVectorEnv` (B = 1) with the standard single-env API."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, **kwargs):
        self._vec = DenoisingVectorEnv(num_envs=1, render_mode=render_mode, **kwargs)
        self.observation_space = self._vec.single_observation_space
        self.action_space = self._vec.single_action_space
        self.render_mode = render_mode

    @property
    def stats(self) -> DatasetStats:
        return self._vec.stats

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        obs, info = self._vec.reset(seed=seed, options=options)
        return {k: v[0] for k, v in obs.items()}, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self._vec.step(np.asarray(action)[None])
        if "scene" in info:
            info = {**info, "terms": {k: float(v[0]) for k, v in info["terms"].items()},
                    "scene": info["scene"].to_layouts()[0]}
        return {k: v[0] for k, v in obs.items()}, float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        frames = self._vec.render()
        return None if frames is None else frames[0]


def register_envs() -> None:
    """Register ``iARCS-Bedroom-v0``, ``iARCS-LivingRoom-v0`` and ``iARCS-DiningRoom-v0``."""
    from .rooms import ROOMS

    for room in ROOMS.values():
        env_id = f"iARCS-{room.gym_name}-v0"
        if env_id in gym.registry:
            continue
        gym.register(env_id, entry_point="rewards.environments:make_env",  # (the reward is handed in there)
                     vector_entry_point="rewards.environments:make_vector_env", kwargs={"room": room.name})
