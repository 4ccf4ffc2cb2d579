"""The task gradient and the searched rooms learned in the same updates, not in turns. ``iarcs train`` on a
physics-gradient config, each update's loss plus ``--weight`` x the mean square of the adapter's x0_hat against
``--batch`` rooms of the ``search_sft.py --cache`` files (each noised to a uniform timestep, their classes given, as
``search_sft.fine_tune`` regresses). In turns (``search_sft.py``, then ``iarcs train``), each fine-tuning undoes much
of what the gradient taught: the wheelchair adapter fine-tuned on its own samples loses 6-13 points
(``self_distill.py --keep all``; docs/results/stage2_tasks.md, "What the fine-tuning costs").

    .venv/bin/python research/joint_expert.py CONFIG.yaml --weight 1 --batch 256 --cache ROOMS.pt [--cache ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from search_sft import cached_rooms, cat, denoising_square  # noqa: E402
import agents.physics_gradient as pg  # noqa: E402
from agents.train import load_train_config, run  # noqa: E402


class ExpertRooms:
    """The searched rooms, model-encoded, and the regression of a policy's x0_hat onto a random batch of them."""

    def __init__(self, policy, rooms, batch: int, seed: int = 7):
        prior = policy.prior
        self.policy, self.batch = policy, batch
        self.x0, self.cond = rooms.encode(prior.stats), prior.floor_condition(rooms.floors)
        self.classes, self.weights = rooms.labels, pg.adapted_object_weights(policy, self.x0)
        self.generator = torch.Generator().manual_seed(seed)

    def square(self) -> torch.Tensor:
        """Mean square of x0_hat against ``batch`` of the rooms (their adapted features), at uniform timesteps."""
        g = self.generator
        rows = torch.randint(0, len(self.x0), (self.batch,), generator=g)
        t = torch.randint(0, self.policy.prior.schedule.num_train_timesteps, (self.batch,), generator=g)
        return denoising_square(self.policy, self.x0[rows], self.cond[rows], self.classes[rows], self.weights[rows], t,
                                g)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a physics-gradient training config (its init_adapter, task, out)")
    parser.add_argument("--cache", action="append", required=True, help="a search_sft.py --cache file (repeatable)")
    parser.add_argument("--weight", type=float, default=1.0, help="the regression's weight beside the gradient's loss")
    parser.add_argument("--batch", type=int, default=256, help="searched rooms regressed onto in each update")
    args = parser.parse_args(argv)
    cfg = load_train_config(args.config)
    if cfg.algorithm != "physics-gradient":
        raise SystemExit(f"{args.config}: algorithm must be physics-gradient, got {cfg.algorithm!r}")
    train, penalty, expert = pg.PhysicsGradient.train, pg.config_penalty, {}

    def joint_train(self, rollout):
        if not expert:
            rooms = cat([cached_rooms(c, self.policy.prior.spec, cfg) for c in args.cache])
            expert["rooms"] = ExpertRooms(self.policy, rooms, args.batch)
            print(f"{len(rooms)} searched rooms regressed onto beside the gradient", flush=True)
        return train(self, rollout)

    def joint_penalty(*a, **kw):  # the gradient's per-scene penalty, plus the regression (the same for each scene)
        return penalty(*a, **kw) + args.weight * expert["rooms"].square()

    pg.PhysicsGradient.train, pg.config_penalty = joint_train, joint_penalty
    try:
        run(cfg)
    finally:
        pg.PhysicsGradient.train, pg.config_penalty = train, penalty


if __name__ == "__main__":
    main()
