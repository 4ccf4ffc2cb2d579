"""Run by tests/test_distributed.py under ``torchrun`` (CPU processes, gloo). Each rank writes what it computed to
``OUT/rank<r>.pt``; the test compares the ranks with each other and with one process."""

import sys
from pathlib import Path

import torch
from tensordict import TensorDict

from agents import distributed
from rewards.composite import CompositeReward
from rewards.sandbox import SandboxedReward
from test_ddpo import STEPS, adapter_weights, make_model

ROWS = 8
BEDS = "def reward(scene):\n    return scene.count('bed')\n"
NIGHTSTANDS = "def reward(scene):\n    return scene.count('nightstand')\n"


def fixed_batch(model) -> TensorDict:
    """The same transitions on every rank (seeded), with non-trivial advantages."""
    g = torch.Generator().manual_seed(5)
    x = torch.randn(ROWS, 12, 30, generator=g)
    floor = torch.from_numpy(model.venv._floor_features[:1]).repeat(ROWS, 1, 1)
    t = torch.full((ROWS, 1), 800)
    action, log_prob = model.policy.act(x, t, floor, generator=torch.Generator().manual_seed(6))
    action = action + 0.01 * torch.randn(action.shape, generator=g)  # off the mean: ratios not 1
    return TensorDict({"x_t": x, "t": t, "floor": floor, "action": action, "sample_log_prob": log_prob,
                       "advantage": torch.randn(ROWS, 1, generator=g)}, batch_size=[ROWS])


def gradients(model, batch) -> list[torch.Tensor]:
    params = model.policy.trainable_parameters()
    for p in params:
        p.grad = None
    loss, _ = model.policy_loss(batch)
    loss.backward()
    return params


def main(out: Path) -> None:
    distributed.setup("cpu")
    r, n = distributed.rank(), distributed.world_size()
    model = make_model()
    batch = fixed_batch(model)

    # the gradient of this rank's share of the batch, averaged over the ranks, and of the whole batch
    params = gradients(model, batch[r * ROWS // n:(r + 1) * ROWS // n])
    distributed.average_gradients(params)
    averaged = [p.grad.clone() for p in params]
    whole = [p.grad.clone() for p in gradients(model, batch)]

    # advantages of rewards that differ per rank, standardised over every rank's
    rewards = torch.arange(ROWS, dtype=torch.float32) * (r + 1) + r
    floor_index = torch.tensor([0, 0, 1, 1, 2, 2, 3, 3]) + 2 * r  # floors 2 and 3 on both ranks
    advantages = model.compute_advantages(rewards, floor_index)

    # two epochs of DDPO: each rank collects its own scenes, all keep one adapter
    before = adapter_weights(model)
    model.learn(8 * STEPS * 2)

    # a reflection on rank 0 swaps the task program and its weight; the other ranks follow
    task = SandboxedReward(BEDS)
    model.venv.reward_fn = CompositeReward({"collision": 1.0, "task": 1.0}, rewards={"task": task})
    if r == 0:
        assert task.load(NIGHTSTANDS).ok
        model.venv.reward_fn.weights["task"] = 2.5
    model._sync_reward()
    followed = {"code": task.code, "weights": dict(model.venv.reward_fn.weights)}
    task.close()

    torch.save({"averaged": averaged, "whole": whole, "rewards": rewards, "floor_index": floor_index,
                "advantages": advantages, "before": before, "after": adapter_weights(model),
                "scene": model._last_scene.translations.clone(), "epoch": model.epoch, "reward": followed},
               out / f"rank{r}.pt")
    distributed.cleanup()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
