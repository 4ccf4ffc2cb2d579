"""How fast DDPO learns a reward that only placement can change, with and without ``ddpo.x0_baseline``.

    .venv/bin/python research/placement_learning.py [--epochs 60] [--threads 1]

The quick stage-1 config (experiments/stage1_bedroom_quick.yaml: the shipped bedroom prior, 32 scenes per
epoch, 4 per floor plan, 20 DDIM steps) with a placement-only adapter (``adapt: [position, yaw]``: which
objects a room holds and their sizes stay the prior's) and, as the only reward, the mean x coordinate (m) of
the ground objects. Both runs use the same seed and learning rate (1e-3); the only difference is the
advantage: one per scene, normalised per floor plan (DDPO), or one per step against the reward of that
step's predicted clean scene (x0_baseline). Prints the rollouts' mean reward per sixth of the run and the
gain (last sixth minus first) of each run as a ratio to the plain run's, all measured in this run.
``--gae-lambda 0.5 0`` adds x0_baseline runs with ``ddpo.gae_lambda`` (per-step credit for each step's own
change of the predicted scene's reward).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.train import build, load_train_config  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "experiments" / "stage1_bedroom_quick.yaml"


def mean_ground_x(scene) -> torch.Tensor:
    """Mean x (m) of each scene's ground objects: a reward that moving objects alone changes."""
    m = scene.ground_mask.float()
    return (scene.translations[..., 0] * m).sum(1) / m.sum(1).clamp(min=1)


def run(options: dict, epochs: int) -> list[float]:
    """The rollouts' mean reward of each epoch, with ``options`` added to the config's DDPO fields."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_train_config(CONFIG, out=tmp)
        cfg.reward, cfg.adapt = {}, ["position", "yaw"]
        cfg.ddpo = {**cfg.ddpo, "learning_rate": 1e-3, **options}
        algo, _, _ = build(cfg, task_reward=mean_ground_x)
        rewards = []
        for _ in range(epochs):
            algo.learn(algo.num_timesteps + 1)  # one epoch
            rewards.append(float(np.mean(algo._last_terms["task"])))
        return rewards


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--gae-lambda", type=float, nargs="*", default=[],
                    help="also run x0_baseline with each of these ddpo.gae_lambda values")
    ap.add_argument("--json", default="out/research/placement_learning.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    k = max(args.epochs // 6, 1)
    runs = {"DDPO": {}, "x0_baseline": {"x0_baseline": True}}
    runs.update({f"gae_lambda={lam:g}": {"x0_baseline": True, "gae_lambda": lam} for lam in args.gae_lambda})
    rows = {}
    for name, options in runs.items():
        r = run(options, args.epochs)
        sixths = [float(np.mean(r[i:i + k])) for i in range(0, len(r) - k + 1, k)]
        rows[name] = {"per_epoch": r, "sixths": sixths, "gain": sixths[-1] - sixths[0]}
        print(f"{name:16s} mean x (m) per sixth of {args.epochs} epochs: " + " ".join(f"{v:+.3f}" for v in sixths))
    plain = rows["DDPO"]["gain"]
    for name, row in rows.items():
        ratio = row["gain"] / plain if plain else float("inf")
        print(f"gain over the run: {name:16s} {row['gain']:+.3f} m ({ratio:.1f}x DDPO's)")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
