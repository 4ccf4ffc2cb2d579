"""How much of DDPO's gradient is signal: per config, the policy-gradient estimate of several independent rollout
batches at the start of training (the config's init adapter), and how far they agree.

    .venv/bin/python research/gradient_noise.py CONFIG [CONFIG ...] [--batches 8]

For each batch k, g_k is the gradient of DDPO's clipped surrogate at ratio 1 (so -mean(A grad log pi)) over every
stochastic step of the batch's chains, in the adapter's LoRA weights. Printed per config: the mean norm of g_k, the
mean cosine between two batches' gradients, and the signal share, an unbiased estimate of |E g|^2 / E|g|^2 from
|mean_k g_k|^2 - (mean_k |g_k - mean|^2) / (K - 1). A share near 0 means one batch's update is almost all noise: an
adapter that starts at its reward's optimum then walks away from it.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.train import _setup_task, build, load_train_config  # noqa: E402


def batch_gradient(algo, rollout, chunk: int = 64) -> torch.Tensor:
    """The flattened gradient of DDPO's loss over every stochastic step of ``rollout`` (its advantages set)."""
    params = algo.policy.trainable_parameters()
    flat = rollout[:, algo.stochastic_steps()].reshape(-1)
    algo.optimizer.zero_grad(set_to_none=True)
    for start in range(0, flat.batch_size[0], chunk):
        part = flat[start:start + chunk]
        loss, _ = algo.policy_loss(part)
        (loss * part.batch_size[0] / flat.batch_size[0]).backward()
    return torch.cat([p.grad.reshape(-1) for p in params]).double()


def gradient_statistics(grads: torch.Tensor) -> dict[str, float]:
    """Mean norm, mean pairwise cosine and signal share (module doc) of K gradients (K, P)."""
    k = grads.shape[0]
    unit = grads / grads.norm(dim=1, keepdim=True)
    cos = unit @ unit.T
    mean = grads.mean(0)
    spread = ((grads - mean) ** 2).sum(1).mean() * k / (k - 1)  # unbiased E|g - E g|^2
    signal = (mean.pow(2).sum() - spread / k) / (grads.pow(2).sum(1).mean())
    return {"norm": float(grads.norm(dim=1).mean()), "cosine": float((cos.sum() - k) / (k * (k - 1))),
            "signal_share": float(signal)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("configs", nargs="+", help="training YAMLs")
    p.add_argument("--batches", type=int, default=8, help="independent rollout batches per config (default 8)")
    args = p.parse_args()
    if args.batches < 2:
        p.error("--batches must be at least 2")
    torch.set_num_threads(1)
    for path in args.configs:
        with tempfile.TemporaryDirectory() as tmp:
            cfg = load_train_config(path, out=tmp)
            task = _setup_task(cfg, Path(tmp), None, log=lambda *a: None) if cfg.task else None
            algo, _, _ = build(cfg, **({} if task is None else task["build"]))
            try:
                grads, rewards = [], []
                for _ in range(args.batches):
                    rollout = algo.collect_rollouts()
                    algo.set_advantages(rollout)
                    grads.append(batch_gradient(algo, rollout))
                    rewards.append(float(rollout["reward"][:, 0].mean()))
            finally:
                if task is not None:
                    task["reward"].sandbox.close()
        stats = gradient_statistics(torch.stack(grads))
        print(f"{path}: {args.batches} batches of {cfg.num_envs} scenes, reward {sum(rewards) / len(rewards):.3f}; "
              f"gradient norm {stats['norm']:.2e}, mean cosine between batches {stats['cosine']:+.3f}, "
              f"signal share {stats['signal_share']:+.3f}")


if __name__ == "__main__":
    main()
