"""Descent imitation: the adapter learns the rooms that the physics penalty's descent leads to, not one step of it.

Each epoch the policy's own rooms (the rollouts' final x_0) are moved down the penalty of
:func:`~agents.physics_gradient.layout_penalty` (the run's weights, as :mod:`agents.physics_gradient` uses them)
by ``descent_steps`` steps of Adam (:data:`DESCENT_LR` m) on each object's floor position (x, z; sizes, heights,
yaws and classes kept). The move dx_0 = x_0* - x_0 (in model features) is then added to the clean scene the policy
predicts at the states x_t of the last ``gradient_steps`` steps of the same rollout, the last being the step at
t = 0 whose x0_hat is the room sampled:

    loss = mean over the adapted features of the rooms' objects of  || x0_hat_theta(x_t, t) - (x0_hat_old + dx_0) ||^2

with x0_hat_old the policy's prediction before the epoch's update. It is the policy-improvement step of expert
iteration (RAFT's reward-ranked fine-tuning, with the ranking replaced by the reward's own descent): the policy
regresses onto its own samples, improved. The target is its own prediction moved, not the room x_0* itself: at
t = 150 the room the chain will end in still differs from x0_hat by the noise the later steps add (a mean square of
0.05 per translation feature on the living-room prior), which swamped the move; regressed onto x_0* itself, the
adapter diverged at learning rate 1e-3 and stood still at 1e-4 (docs/results/stage1_living_dining.md).

Why: the physics gradient moves x0_hat of the last denoising steps one gradient step per update; on the living-room
prior its adapters lowered the penalty but not Col_obj (49.1% -> 46-49%), while descent on the prior's own rooms
reaches a third fewer colliding objects with more of them reachable (``research/layout_descent.py``;
docs/results/stage1_living_dining.md). Measured there: this adapter fits the moves of the rooms it is shown but
carries them over to new rooms only after thousands of them (``research/descent_fit.py``,
``research/descent_offline.py``); not shipped. The walkway term
(``reach_weight``) charges the clearance at each object's path bottleneck (:func:`iarcs_env.clearance.reach_points`),
searched for again every :data:`REACH_REFRESH` steps.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from iarcs_env import geometry as geo
from iarcs_env.clearance import clearance_of_points, reach_points
from iarcs_env.scene import decode_geometry, floor_half_extents, translation_scale

from . import distributed
from .physics_gradient import PhysicsGradient, adapted_object_weights, layout_penalty, penalty_weights

DESCENT_LR = 0.01
"""m: Adam's step on the objects' positions."""
REACH_REFRESH = 20
"""Descent steps between searches of the walkways' bottleneck points (each search grids the rooms: seconds)."""


def descend_layouts(trans: torch.Tensor, half: torch.Tensor, yaws: torch.Tensor, labels: torch.Tensor, spec, floors,
                    steps: int, reach_weight: float = 0.0, lr: float = DESCENT_LR, refresh: int = REACH_REFRESH,
                    **weights) -> torch.Tensor:
    """Translations (B, N, 3) moved on the floor (x, z) by ``steps`` steps of Adam down :func:`layout_penalty` of
    the rooms (``weights``: its keyword arguments) plus ``reach_weight`` times each ground object's walkway
    shortfall (m), the clearance at its path bottleneck point (found again every ``refresh`` steps)."""
    trans0, half, yaws = trans.detach().double(), half.detach().double(), yaws.detach().double()
    valid = labels != spec.empty_index
    ground = torch.tensor(spec.ground_mask())[labels] & valid
    delta = torch.zeros(trans0.shape[:2] + (2,), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=lr)
    points = None

    def moved_by(d: torch.Tensor) -> torch.Tensor:  # the objects' x and z shifted, heights kept, empty slots still
        move = d * valid[..., None]
        return trans0 + torch.stack([move[..., 0], torch.zeros_like(move[..., 0]), move[..., 1]], -1)

    for step in range(steps):
        moved = moved_by(delta)
        loss = layout_penalty(moved, half, yaws, labels, spec, floors, **weights)
        if reach_weight:
            if step % refresh == 0:
                points = reach_points(floors, moved.detach(), half, yaws, ground, geo.AGENT_RADIUS)
            clear = clearance_of_points(floors, points, moved, half, yaws, ground, geo.AGENT_RADIUS)
            loss = loss + reach_weight * (geo.AGENT_RADIUS - clear).clamp_min(0).sum(1)
        optimizer.zero_grad()
        loss.sum().backward()
        optimizer.step()
    return moved_by(delta.detach()).to(trans.dtype)


class DescentImitation(PhysicsGradient):
    """Descent imitation (module doc) with :class:`~agents.ddpo.DDPO`'s surface. Uses ``descent_steps`` and the
    penalty's weights and measures of :class:`~agents.physics_gradient.PhysicsGradient` (``overlap_weight``,
    ``overlap_measure``, ``contact_gap_weight``, ``contact_gap``, ``uncharged_pairs``, ``reach_weight``,
    ``out_of_bound_weight``, ``out_of_bound_shrink``), and ``learning_rate``, ``minibatch_size``,
    ``num_inner_epochs``, ``max_grad_norm`` and ``gradient_steps``."""

    name = "DESCENT-IMITATION"

    def __init__(self, policy, env, **kwargs):
        super().__init__(policy, env, **kwargs)
        if self.config.descent_steps < 1:
            raise ValueError(f"descent_steps must be at least 1 (the Adam steps that move the rooms the adapter "
                             f"learns); got {self.config.descent_steps}")
        if self.task_reward() is not None:
            raise ValueError("descent-imitation moves rooms down the physical penalty only; train a task with "
                             "physics-gradient or ddpo")

    def targets(self, x0: torch.Tensor, floors) -> tuple[torch.Tensor, dict[str, float]]:
        """The move dx_0 (B, N, 8 + K) in model features that takes the rooms ``x0``'s objects down the penalty
        (module doc; zero but for the translations' x and z), and the penalty's mean before and after."""
        cfg, stats = self.config, self.venv.stats
        spec = stats.spec
        extents = floor_half_extents(floors)
        trans, half, yaws = decode_geometry(x0, stats, extents)
        labels = x0[..., 8:].argmax(-1)
        weights = penalty_weights(cfg, self.contact())
        moved = descend_layouts(trans, half, yaws, labels, spec, floors, cfg.descent_steps, cfg.reach_weight,
                                **weights)
        lo, hi = translation_scale(stats, x0, extents, half, yaws)
        move = torch.zeros_like(x0)
        now = x0[..., 0:3].clamp(-1, 1)  # decoding is linear in the translation features inside [-1, 1]
        move[..., 0:3] = (now + 2 * (moved - trans) / (hi - lo)).clamp(-1, 1) - now
        penalty = {name: float(layout_penalty(t, half, yaws, labels, spec, floors, **weights).mean())
                   for name, t in (("before", trans), ("after", moved))}
        return move, {"physics": penalty["before"], "physics_descended": penalty["after"]}

    def train(self, rollout: TensorDict) -> dict[str, float]:
        cfg, venv, policy = self.config, self.venv, self.policy
        last = rollout[:, -1]
        floors = [venv.floors[int(i)] for i in last["floor_index"]]
        given = "classes" in last.keys()
        x0 = policy.prior.with_clean_classes(last["action"], last["classes"]) if given else last["action"]
        move, info = self.targets(x0, floors)
        weight = adapted_object_weights(policy, x0)
        info["move_square"] = float((move.square() * weight).sum() / weight.sum().clamp_min(1))
        states = rollout[:, -cfg.gradient_steps:].reshape(-1).to(self.device)  # the states the policy visited

        batch = cfg.minibatch_size * cfg.gradient_steps

        def predict(rows: torch.Tensor) -> torch.Tensor:  # an object against a wall can still be pulled off it
            mb = states[rows]
            return policy.predict_x0(mb["x_t"], mb["t"], mb["floor"], mb["classes"] if given else None,
                                     straight_through=True)

        policy.model.eval()
        with torch.no_grad():  # the targets: the predictions before this update, moved
            target = torch.cat([predict(rows) for rows in torch.arange(len(states)).split(batch)])
        target = target + move.to(self.device).repeat_interleave(cfg.gradient_steps, 0)
        weight = weight.to(self.device).repeat_interleave(cfg.gradient_steps, 0)
        losses = []
        for _ in range(cfg.num_inner_epochs):
            perm = torch.randperm(len(states), generator=self.generator)
            for rows in perm.split(batch):
                w = weight[rows]
                loss = ((predict(rows) - target[rows]).square() * w).sum() / w.sum().clamp_min(1)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                distributed.average_gradients(policy.trainable_parameters())
                torch.nn.utils.clip_grad_norm_(policy.trainable_parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                losses.append(loss.item())
        return {**info, "loss": sum(losses) / len(losses), "approx_kl": 0.0, "clip_fraction": 0.0}
