"""Reward-ranked fine-tuning (RAFT, Dong et al. 2023; expert iteration as in ReST): the LoRA adapter is
trained with the prior's own DDPM loss on the best final scenes of its own rollouts.

Each epoch the rollouts' final scenes x_0 are ranked by their advantage (the reward standardised per floor
plan, or each term standardised and weighted with ``per_term_advantages``). The top ``elite_fraction`` of them,
cleaned (classes one-hot, as in the training data), are the epoch's data for the DDPM loss

    loss = E_{t, eps} || eps - eps_theta(sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps, t, floor) ||^2

with round(timestep_fraction * S) noise levels t per scene (S: the DDIM steps of a rollout). A policy gradient
moves each step's Gaussian by the advantage of one chain; this moves the whole denoiser towards the scenes the
reward ranks first, the mid-noise steps included, where a room's arrangement is decided. It uses
:class:`~agents.ddpo.DDPO`'s rollouts, evaluation, checkpoints and callbacks; only the update differs.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from iarcs_env.scene import SceneBatch, floor_half_extents

from . import distributed
from .ddpo import ALGORITHMS, DDPO
from .pretrain import SceneTensors, encode_batch


class RewardRankedFineTuning(DDPO):
    """RAFT (module doc) with :class:`DDPO`'s surface. Uses ``elite_fraction``, ``timestep_fraction``,
    ``learning_rate``, ``minibatch_size`` (elite scenes per step), ``num_inner_epochs``, ``max_grad_norm`` and
    ``kl_coef`` (a KL penalty to the reference policy on ``minibatch_size`` of the rollout's transitions per
    step), ``anchor_data`` and ``anchor_scenes`` of :class:`~agents.ddpo.DDPOConfig`; the last three hold the
    policy back from the drift of training on its own samples."""

    name = "RAFT"

    def __init__(self, policy, env, **kwargs):
        super().__init__(policy, env, **kwargs)
        if not 0 < self.config.elite_fraction <= 1:
            raise ValueError(f"elite_fraction must be in (0, 1], got {self.config.elite_fraction}")
        self.anchor = self._load_anchor() if self.config.anchor_data else None

    def _load_anchor(self) -> SceneTensors:
        """The ``anchor_data`` rooms as metric tensors (rooms with more objects than slots left out)."""
        from iarcs_env.datasets import load_layouts

        from .pretrain import resolve_dataset

        spec, cfg = self.venv.stats.spec, self.config
        layouts = load_layouts(resolve_dataset(cfg.anchor_data), spec.name, num_scenes=cfg.anchor_scenes, seed=0)
        layouts = [l for l in layouts if len(l) <= spec.max_objects][:cfg.anchor_scenes]
        if not layouts:
            raise ValueError(f"anchor_data {cfg.anchor_data!r} holds no {spec.name} rooms with at most "
                             f"{spec.max_objects} objects")
        return SceneTensors.from_layouts(layouts, spec.max_objects)

    def anchor_batch(self, count: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(x_0, floor features) of ``count`` random anchor rooms, rotated and with shuffled slots as in
        pretraining."""
        idx = torch.randint(len(self.anchor), (count,), generator=self.generator)
        batch = self.anchor.batch(idx, self.generator, rotate=True, permute=True)
        return encode_batch(self.venv.stats.spec, self.venv.stats, *batch)

    def elite_scenes(self, rollout: TensorDict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(x_0, floor features, indices in the rollout) of the top ``elite_fraction`` of the rollout's scenes by
        advantage (the reward standardised per floor plan; per term with ``per_term_advantages``); x_0 is
        re-encoded from the decoded scenes, so classes are exact one-hots."""
        if "advantage" not in rollout.keys():
            self.set_advantages(rollout)
        score = rollout["advantage"][:, -1, 0]
        floor_index = rollout["floor_index"][:, 0]
        k = max(1, int(round(self.config.elite_fraction * len(score))))
        top = score.argsort(descending=True)[:k]
        floors = [self.venv.floors[int(i)] for i in floor_index[top]]
        scenes = SceneBatch.decode(rollout["action"][top, -1], self.venv.stats, floors)
        return scenes.encode(self.venv.stats, floor_half_extents(floors)), rollout["floor"][top, 0], top

    def train(self, rollout: TensorDict) -> dict[str, float]:
        cfg = self.config
        x0, floor, elites = self.elite_scenes(rollout)
        levels = max(1, int(round(cfg.timestep_fraction * self.venv.num_steps)))
        schedule, steps = self.policy.schedule, self.stochastic_steps()
        infos = []
        self.policy.model.eval()
        for _ in range(cfg.num_inner_epochs):
            perm = torch.randperm(len(x0), generator=self.generator)
            for start in range(0, len(x0), cfg.minibatch_size):
                rows = perm[start:start + cfg.minibatch_size].repeat_interleave(levels)
                x, f = x0[rows], floor[rows]
                if self.anchor is not None:
                    x_data, f_data = self.anchor_batch(len(rows))
                    x, f = torch.cat([x, x_data]), torch.cat([f, f_data])
                x, f = x.to(self.device), f.to(self.device)
                loss = schedule.training_loss(lambda x_t, t: self.policy.eps(x_t, t, f), x, self.generator)
                info = {}
                if cfg.kl_coef > 0:  # anchored to the reference policy on the rollout's own states
                    rows = torch.randint(rollout.batch_size[0], (cfg.minibatch_size,), generator=self.generator)
                    cols = steps[torch.randint(len(steps), (cfg.minibatch_size,), generator=self.generator)]
                    kl = self.kl_to_base(rollout[rows, cols].to(self.device))
                    loss = loss + cfg.kl_coef * kl
                    info["kl_to_base"] = kl.item()
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                distributed.average_gradients(self.policy.trainable_parameters())
                grad_norm = torch.nn.utils.clip_grad_norm_(self.policy.trainable_parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                infos.append({**info, "loss": loss.item(), "grad_norm": float(grad_norm)})
        stats = {key: float(np.mean([i[key] for i in infos])) for key in infos[0]}
        return {**stats, "elite_reward": float(rollout["reward"][elites, 0].mean()), "approx_kl": 0.0,
                "clip_fraction": 0.0}


ALGORITHMS[RewardRankedFineTuning.name] = RewardRankedFineTuning
