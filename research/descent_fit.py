"""Can a descent-imitation adapter (``agents/descent_imitation.py``) learn the descent's moves, and do they carry over
to rooms it did not see? One batch of the config's rollouts from the prior, their rooms descended once, then
``--updates`` passes of the algorithm's regression on that batch alone (targets fixed): how much of the move the
final step's prediction takes (the miss: the squared distance of the x and z features from prediction + move, summed
over the objects), the penalty of those predictions, and on ``--floors`` other floors (seed 4242, the noise fixed)
the penalty and Col_obj of the rooms sampled with the adapter and without it (the prior).

    .venv/bin/python research/descent_fit.py experiments/ablations/stage1_livingroom_descent.yaml --updates 50
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling script

from agents.physics_gradient import penalty_weights, physics_penalty  # noqa: E402
from agents.train import build, load_train_config  # noqa: E402
from descent_offline import held_out_floors, sampled_on  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a descent-imitation training config")
    parser.add_argument("--updates", type=int, default=50, help="passes over the one batch (num_inner_epochs)")
    parser.add_argument("--reach-weight", type=float, help="override ddpo.reach_weight (0: no walkway term)")
    parser.add_argument("--floors", type=int, default=64, help="other floors, sampled with and without the adapter")
    args = parser.parse_args(argv)
    overrides = {"num_inner_epochs": args.updates}
    if args.reach_weight is not None:
        overrides["reach_weight"] = args.reach_weight
    cfg = load_train_config(args.config)
    cfg.ddpo.update(overrides)
    algo, policy, _ = build(cfg)
    stats, weights = algo.venv.stats, penalty_weights(algo.config, algo.contact())

    other = held_out_floors(cfg.room, args.floors)
    rollout = algo.collect_rollouts()
    last = rollout[:, -1]
    floors = [algo.venv.floors[int(i)] for i in last["floor_index"]]
    move, info = algo.targets(last["action"], floors)
    real = (last["action"][..., 8:].argmax(-1) != stats.spec.empty_index)[..., None]

    def final_prediction() -> torch.Tensor:
        with torch.no_grad():
            return policy.predict_x0(last["x_t"], last["t"], last["floor"])

    before = final_prediction()
    miss = lambda x: float(((x - before - move)[..., [0, 2]] * real).square().sum())  # noqa: E731
    print(f"{len(floors)} rooms: penalty {info['physics']:.3f}, descended {info['physics_descended']:.3f}; "
          f"final prediction's miss {miss(before):.3f}")
    algo.train(rollout)
    after = final_prediction()
    print(f"after {args.updates} passes: miss {miss(after):.3f}, "
          f"final prediction's penalty {float(physics_penalty(after, stats, floors, **weights).mean()):.3f}")
    print(f"{args.floors} other floors, with the adapter: {sampled_on(policy, cfg, other, weights)}")
    with policy.base_policy():
        print(f"{args.floors} other floors, the prior: {sampled_on(policy, cfg, other, weights)}")


if __name__ == "__main__":
    main()
