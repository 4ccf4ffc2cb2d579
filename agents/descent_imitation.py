"""Descent imitation: the adapter learns the rooms that the physics penalty's descent leads to, not one step of it.

Each epoch the policy's own rooms (the rollouts' final x_0) are moved down the penalty of
:func:`~agents.physics_gradient.layout_penalty` (the run's weights, as :mod:`agents.physics_gradient` uses them)
by ``descent_steps`` steps of Adam (:data:`DESCENT_LR` m) on each object's floor position (x, z; sizes, heights,
yaws and classes kept). The moved room x_0* is the target of the clean scene the policy predicts at the states x_t
of the last ``gradient_steps`` stochastic steps of the same rollout (where :mod:`agents.physics_gradient` applies
the penalty's gradient):

    loss = mean over the adapted features of the rooms' objects of  || x0_hat_theta(x_t, t) - x_0* ||^2

It is the policy-improvement step of expert iteration (RAFT's reward-ranked fine-tuning, with the ranking replaced
by the reward's own descent): the policy regresses onto its own samples, improved. On the states it visited, not on
fresh noise of a pretraining loss: the scene's noise is then the rollout's own, and the loss's gradient is the
room's move, not the denoising error of a random draw (a first run with that loss, on the living-room prior, had not
moved Col_obj in 10 epochs).

Why: the physics gradient moves x0_hat of the last denoising steps one gradient step per update; on the living-room
prior its adapters lowered the penalty but not Col_obj (49.1% -> 46-49%), while descent on the prior's own rooms
reaches a third fewer colliding objects with more of them reachable (``research/layout_descent.py``;
docs/results/stage1_living_dining.md). Measured there: this adapter, 11 epochs on that prior, learned the move
common to the rooms (furniture towards the walls) and not each room's own; not shipped. The walkway term
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
from .physics_gradient import PhysicsGradient, layout_penalty, penalty_weights

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
        """The rooms ``x0`` (B, N, 8 + K) with their objects moved down the penalty (module doc), and the penalty's
        mean before and after."""
        cfg, stats = self.config, self.venv.stats
        spec = stats.spec
        extents = floor_half_extents(floors)
        trans, half, yaws = decode_geometry(x0, stats, extents)
        labels = x0[..., 8:].argmax(-1)
        weights = penalty_weights(cfg, self.contact())
        moved = descend_layouts(trans, half, yaws, labels, spec, floors, cfg.descent_steps, cfg.reach_weight,
                                **weights)
        lo, hi = translation_scale(stats, x0, extents, half, yaws)
        target = x0.clone()  # the translation features that decode to the moved positions (decoding clamps them)
        target[..., 0:3] = x0[..., 0:3].clamp(-1, 1) + 2 * (moved - trans) / (hi - lo)
        penalty = {name: float(layout_penalty(t, half, yaws, labels, spec, floors, **weights).mean())
                   for name, t in (("before", trans), ("after", moved))}
        return target, {"physics": penalty["before"], "physics_descended": penalty["after"]}

    def train(self, rollout: TensorDict) -> dict[str, float]:
        cfg, venv, policy = self.config, self.venv, self.policy
        last = rollout[:, -1]
        floors = [venv.floors[int(i)] for i in last["floor_index"]]
        given = "classes" in last.keys()
        x0 = policy.prior.with_clean_classes(last["action"], last["classes"]) if given else last["action"]
        target, info = self.targets(x0, floors)
        keep = policy.reference_features(policy.adapter)
        adapted = torch.ones(target.shape[-1], dtype=torch.bool) if keep is None else ~keep
        weight = ((target[..., 8:].argmax(-1) != venv.stats.spec.empty_index)[..., None] & adapted).float()
        steps = self.stochastic_steps()[-cfg.gradient_steps:]
        losses = []
        policy.model.eval()
        for _ in range(cfg.num_inner_epochs):
            perm = torch.randperm(len(target), generator=self.generator)
            for start in range(0, len(target), cfg.minibatch_size):
                rows = perm[start:start + cfg.minibatch_size]
                mb = rollout[rows][:, steps].to(self.device)  # the states the policy visited, (b, k)
                x0_hat = policy.predict_x0(mb["x_t"].flatten(0, 1), mb["t"].flatten(0, 1), mb["floor"].flatten(0, 1),
                                           mb["classes"].flatten(0, 1) if given else None)
                x0_star = target[rows].to(self.device).repeat_interleave(len(steps), 0)
                w = weight[rows].to(self.device).repeat_interleave(len(steps), 0)
                loss = ((x0_hat - x0_star).square() * w).sum() / w.sum().clamp_min(1)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                distributed.average_gradients(policy.trainable_parameters())
                torch.nn.utils.clip_grad_norm_(policy.trainable_parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                losses.append(loss.item())
        return {**info, "loss": sum(losses) / len(losses), "approx_kl": 0.0, "clip_fraction": 0.0}
