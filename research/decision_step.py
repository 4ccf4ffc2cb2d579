"""At which denoising step does a room choose which way its bed faces? For tv_from_bed the choice decides the task
(a bed facing a wall less than 2.3 m away nearly never passes: ``research/tv_bed_facing.py``), and it differs
between samples of the same floor. Rolls out a run's adapter (its ``init_adapter`` with its required objects) on
``--floors`` training floors, ``--samples`` times each, and prints, per step, how often the bed of the clean scene
that step predicts (x0_hat) faces the same way (the floor ahead of it under or over 2.3 m) as the final room's bed.

    .venv/bin/python research/decision_step.py CONFIG [--floors 64 --samples 4]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from agents.train import build, load_train_config  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402
from tv_bed_facing import NARROW, room_ahead  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a training config whose init_adapter is the adapter to roll out")
    parser.add_argument("--floors", type=int, default=64)
    parser.add_argument("--samples", type=int, default=4)
    args = parser.parse_args(argv)
    cfg = load_train_config(args.config)
    cfg.num_envs = args.floors * args.samples
    torch.set_num_threads(1)
    algo, policy, env = build(cfg)
    venv = env.unwrapped
    generator = torch.Generator().manual_seed(0)
    picked = np.arange(args.floors)
    floor_idx = np.repeat(picked, args.samples)
    obs, _ = env.reset(seed=0, options={"floor_indices": floor_idx})
    floors = [venv.floors[i] for i in floor_idx]
    classes = policy.required_classes([venv.floors[i] for i in picked], generator).repeat_interleave(args.samples, 0)
    prior = policy.prior
    facing, ts = [], []
    with torch.no_grad():
        for _ in range(venv.num_steps):
            t = torch.from_numpy(obs["t"])
            x_t = prior.with_classes(torch.from_numpy(obs["x_t"]), t.reshape(-1), classes, generator)
            action, _, x0_hat = policy.act(x_t, t, torch.from_numpy(obs["floor"]), generator=generator,
                                           return_x0=True, classes=classes)
            layouts = SceneBatch.decode(prior.with_clean_classes(x0_hat, classes), venv.stats, floors).to_layouts()
            facing.append([(room_ahead(lay) or 0.0) >= NARROW for lay in layouts])
            ts.append(int(t.reshape(-1)[0]))
            obs, *_ = env.step(action.numpy())
    facing = np.array(facing)
    final = facing[-1]
    print(f"{args.floors} floors x {args.samples} samples: final beds facing {NARROW} m or more of floor "
          f"{final.mean():.1%}; floors whose samples differ {np.mean([len(set(final[floor_idx == f])) > 1 for f in picked]):.0%}")
    for t, row in zip(ts, facing):
        print(f"  t = {t:4d}: x0_hat's bed faces as the final room's {np.mean(row == final):.1%}, wide {row.mean():.1%}")


if __name__ == "__main__":
    main()
