"""Seconds per DDPO epoch (rollout, reward, update) for the small and paper presets, with each phase's share.

    .venv/bin/python benchmarks/bench_ddpo_epoch.py [--scenes 256] [--minibatch 32] [--presets small paper] [--x0-baseline]

One epoch = a rollout of --scenes bedrooms (20 DDIM steps), the universal composite reward on the final
scenes, and one pass of DDPO-IS updates over all stochastic steps (timestep_fraction 1). Weights are random
(timing depends on the architecture, not on training). The figures are printed as ratios against one
forward pass of the same model on the same batch, measured in the same run, so they can be compared across
machines. ``--x0-baseline`` also times each preset with ``ddpo.x0_baseline`` (the reward of every step's
x0_hat, scored during the rollout) and prints its epoch time as a ratio to the plain epoch's.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import torch

import iarcs_env  # noqa: F401
from agents.config import resolve_device
from agents.ddpo import DDPO
from agents.denoiser import ScenePrior
from agents.policy import DiffusionPolicy
from iarcs_env.env import default_floors, default_stats
from rewards.composite import CompositeReward


def make_algo(preset: str, scenes: int, minibatch: int, steps: int = 20, device: str = "cpu",
              x0_baseline: bool = False) -> DDPO:
    """DDPO-IS on a random-weight bedroom prior of ``preset`` with ``scenes`` environments and the universal reward,
    the policy on ``device``."""
    torch.manual_seed(0)
    stats = default_stats("bedroom")
    prior = ScenePrior.create("bedroom", stats, preset)
    with torch.no_grad():  # adaLN-Zero layers start at 0; give them weights so every path does work
        for p in prior.denoiser.parameters():
            if p.dim() == 2 and float(p.abs().sum()) == 0:
                p.normal_(std=0.02)
    policy = DiffusionPolicy(prior, num_steps=steps).to(resolve_device(device))
    reward = CompositeReward.universal(stats)
    env = gym.make_vec("iARCS-Bedroom-v0", num_envs=scenes, vectorization_mode="vector_entry_point",
                       floors=default_floors("bedroom", 64), stats=stats, reward=reward, num_steps=steps)
    return DDPO(policy, env, verbose=0, minibatch_size=minibatch, samples_per_floor=4, x0_baseline=x0_baseline)


def measure(preset: str, scenes: int, minibatch: int, steps: int = 20, device: str = "cpu",
            x0_baseline: bool = False) -> dict:
    algo = make_algo(preset, scenes, minibatch, steps, device, x0_baseline)
    policy, reward, prior, stats = algo.policy, algo.venv.reward_fn, algo.policy.prior, algo.policy.prior.stats
    t0 = time.perf_counter()
    rollout = algo.collect_rollouts()  # includes the reward, timed again below
    t1 = time.perf_counter()
    reward(algo._last_scene)
    t_reward = time.perf_counter() - t1
    algo.set_advantages(rollout)
    t2 = time.perf_counter()
    algo.train(rollout)
    t_update = time.perf_counter() - t2
    t_rollout = (t1 - t0) - t_reward

    x = torch.randn(scenes, 12, stats.spec.feature_dim, device=algo.device)
    f = torch.from_numpy(algo.venv._floor_features[:1]).repeat(scenes, 1, 1).to(algo.device)
    with torch.no_grad():
        t3 = time.perf_counter()
        policy(x, torch.full((scenes,), 500, device=algo.device), f)[0].sum().item()  # .item(): waits for a GPU
        t_forward = time.perf_counter() - t3
    total = t_rollout + t_reward + t_update
    return {"preset": preset, "x0_baseline": x0_baseline, "scenes": scenes, "minibatch": minibatch, "epoch_s": total,
            "rollout_s": t_rollout, "reward_s": t_reward, "update_s": t_update,
            "share_rollout": t_rollout / total, "share_reward": t_reward / total, "share_update": t_update / total,
            "forward_s": t_forward, "epoch_in_forward_passes": total / t_forward,
            "parameters": prior.denoiser.num_parameters()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=256, help="scenes per epoch (DDPO's sample batch; default 256)")
    ap.add_argument("--minibatch", type=int, default=32, help="scenes per optimiser step (default 32)")
    ap.add_argument("--presets", nargs="+", default=["small", "paper"])
    ap.add_argument("--x0-baseline", action="store_true", help="also time each preset with ddpo.x0_baseline")
    ap.add_argument("--device", default="cpu", help="where the policy runs: cpu (default), cuda or cuda:N")
    ap.add_argument("--json", default="out/benchmarks/bench_ddpo_epoch.json")
    args = ap.parse_args()
    try:
        resolve_device(args.device)
    except ValueError as err:
        ap.error(str(err))
    measure(args.presets[0], 4, 4, device=args.device)  # warm-up: first-call costs are not an epoch's
    rows = [measure(p, args.scenes, args.minibatch, device=args.device, x0_baseline=x0)
            for p in args.presets for x0 in ([False, True] if args.x0_baseline else [False])]
    plain = {r["preset"]: r["epoch_s"] for r in rows if not r["x0_baseline"]}
    print(f"{'preset':<7} {'x0_baseline':>11} {'scenes':>6} {'epoch s':>8} {'rollout':>8} {'reward':>7} {'update':>7} "
          f"{'epoch / forward pass':>21} {'epoch / plain epoch':>20}")
    for r in rows:
        print(f"{r['preset']:<7} {str(r['x0_baseline']):>11} {r['scenes']:>6} {r['epoch_s']:>8.1f} "
              f"{100 * r['share_rollout']:>7.0f}% {100 * r['share_reward']:>6.0f}% {100 * r['share_update']:>6.0f}% "
              f"{r['epoch_in_forward_passes']:>20.0f}x {r['epoch_s'] / plain[r['preset']]:>19.2f}x")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
