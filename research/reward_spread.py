"""Which reward term drives DDPO's advantages: the spread of each weighted term within a floor plan's group.

    .venv/bin/python research/reward_spread.py experiments/task_reach_1m.yaml --batches 4

DDPO normalises the total reward per floor plan (``samples_per_floor`` scenes of one floor), so what the
policy learns from is each term's spread *within* those groups, weight included. A term whose weighted
within-floor standard deviation is several times the task term's decides the sign of most advantages,
whatever the task term does; ``ddpo.per_term_advantages`` standardises each term first. Rolls out
``--batches`` batches of the config's policy at its start (the init adapter, or the prior) and prints, per
term: weight, mean raw value, mean within-floor std of the weighted term, and the total std.

``--x0-steps`` adds, per DDIM step, how much of the total reward's within-floor spread the reward of that
step's predicted clean scene x0_hat explains (the ``ddpo.x0_baseline`` fit): where it is near 0 the chain
has not yet decided what the reward depends on, where it is near 1 little is left for later steps to change.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.ddpo import x0_baseline_fit  # noqa: E402
from agents.train import _setup_task, build, load_train_config  # noqa: E402


def within_floor_std(values: torch.Tensor, groups: torch.Tensor) -> float:
    """Mean over groups of the (population) standard deviation of ``values`` within each group."""
    return float(np.mean([values[groups == g].double().std(unbiased=False).item() for g in groups.unique()]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("config", help="a training YAML (experiments/task_*.yaml or stage1_*.yaml)")
    p.add_argument("--batches", type=int, default=4, help="rollout batches of num_envs scenes (default 4)")
    p.add_argument("--x0-steps", action="store_true",
                   help="also print the share of the spread each step's x0_hat reward explains")
    args = p.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_train_config(args.config, out=tmp)
        task = _setup_task(cfg, Path(tmp), None, log=lambda *a: None) if cfg.task else None
        if args.x0_steps:
            cfg.ddpo = {**cfg.ddpo, "x0_baseline": True}
        algo, _, env = build(cfg, **({} if task is None else task["build"]))
        try:
            rollouts = [algo.collect_rollouts() for _ in range(args.batches)]
        finally:
            if task is not None:
                task["reward"].sandbox.close()
    weights = env.unwrapped.reward_fn.weights
    terms = torch.cat([td["terms"][:, 0] for td in rollouts])
    total = torch.cat([td["reward"][:, 0] for td in rollouts])
    # floor indices repeat across batches: make each batch's groups distinct
    groups = torch.cat([td["floor_index"][:, 0] + k * len(env.unwrapped.floors) for k, td in enumerate(rollouts)])
    print(f"{len(total)} scenes, {len(groups.unique())} floor groups; {args.config}")
    print(f"{'term':16s} {'weight':>7s} {'mean':>8s} {'within-floor std (weighted)':>28s} {'total std':>10s}")
    for k, name in enumerate(weights):
        weighted = terms[:, k] * weights[name]
        print(f"{name:16s} {weights[name]:7.2f} {terms[:, k].mean():8.3f} {within_floor_std(weighted, groups):28.3f} "
              f"{weighted.std():10.3f}")
    print(f"{'total':16s} {'':7s} {total.mean():8.3f} {within_floor_std(total, groups):28.3f} {total.std():10.3f}")

    if args.x0_steps:
        values = torch.cat([td["reward_x0_hat"] for td in rollouts])
        _, beta, r2 = x0_baseline_fit(total, values, [groups == g for g in groups.unique()])
        t = rollouts[0]["t"][0, :, 0].tolist()
        print(f"{'step':>4s} {'t':>5s} {'beta':>6s} {'share of the within-floor spread explained by r(x0_hat(x_t))':>60s}")
        for k in range(len(t)):
            print(f"{k:4d} {t[k]:5d} {beta[k]:6.2f} {r2[k]:60.3f}")


if __name__ == "__main__":
    main()
