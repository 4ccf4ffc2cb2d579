"""How far can moving and turning a room's objects take a task? Descent on the layouts themselves, no network: each
room's objects move on the floor (x, z) and turn, by Adam on a training config's loss of the physics-gradient
update (its overlap, out-of-bound and contact terms, ``agents.physics_gradient.layout_penalty``) less its task
weight times the task reward the offline planner writes for the task's prompt (the sandboxed program's own
gradient). Classes, sizes and heights are kept, so an adapter that only moves and turns (``adapt: [position,
yaw]``) has at most this to gain from rooms like these, short of finding a better minimum than Adam does.

    .venv/bin/python research/task_descent.py TASK CONFIG SCENES.json --out DESCENDED.json [--steps 200]
    iarcs evaluate --scenes DESCENDED.json --reference floors.json --task TASK --features none --out report.json

Prints the task's success and the penalty before and after, every 50 steps.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CHUNK = 50
MOVE_LR = 0.02
"""m: Adam's step on the positions."""
TURN_LR = 0.05
"""rad: Adam's step on the yaws."""


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("task", help="a paper task (iarcs_env.tasks): its prompt and its checker")
    parser.add_argument("config", help="a physics-gradient task config (its ddpo weights, contact and task weight)")
    parser.add_argument("scenes", help="rooms to descend (neutral JSON, e.g. stage 1's samples)")
    parser.add_argument("--out", required=True, help="where to write the descended rooms")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--rooms", type=int, help="only the first N rooms")
    args = parser.parse_args(argv)
    import torch
    from tqdm import tqdm

    from agents.ddpo import DDPOConfig
    from agents.physics_gradient import layout_penalty, penalty_weights
    from agents.train import load_train_config
    from iarcs_env.datasets import load_layouts, save_layouts
    from iarcs_env.scene import SceneBatch
    from iarcs_env.tasks import get_task, task_results
    from rewards.agent import make_agent
    from rewards.sandbox import SandboxedReward

    torch.set_num_threads(1)
    cfg = load_train_config(args.config)
    task = get_task(args.task)
    layouts = load_layouts(args.scenes, cfg.room)[:args.rooms]
    collision = cfg.reward.get("collision")
    weights = penalty_weights(DDPOConfig.from_dict(cfg.ddpo), collision.get("contact") if isinstance(collision, dict)
                              else None)
    code = make_agent(None).synthesize(cfg.room, task.prompt).code
    task_weight = cfg.task["weight"]
    out, before, after = [], [], []
    with SandboxedReward(code, room=cfg.room) as reward, tqdm(total=len(layouts) * args.steps, unit="step") as bar:
        for start in range(0, len(layouts), CHUNK):
            batch = SceneBatch.from_layouts(layouts[start:start + CHUNK])
            valid = (batch.labels != batch.spec.empty_index).double()
            trans0, yaw0 = batch.translations.double(), batch.yaws.double()
            move = torch.zeros(trans0.shape[:2] + (2,), dtype=torch.float64, requires_grad=True)
            turn = torch.zeros(yaw0.shape, dtype=torch.float64, requires_grad=True)
            optimizer = torch.optim.Adam([{"params": [move], "lr": MOVE_LR}, {"params": [turn], "lr": TURN_LR}])

            def moved() -> tuple[torch.Tensor, torch.Tensor]:
                d = move * valid[..., None]
                shift = torch.stack([d[..., 0], torch.zeros_like(d[..., 0]), d[..., 1]], -1)
                return trans0 + shift, yaw0 + turn * valid

            def penalty(trans, yaws) -> torch.Tensor:
                return layout_penalty(trans, batch.half_sizes.double(), yaws, batch.labels, batch.spec,
                                      batch.floors, **weights)

            def placed() -> tuple[torch.Tensor, torch.Tensor]:  # the batch's geometry set to the current move
                trans, yaws = moved()
                batch.translations, batch.yaws = trans.detach().float(), yaws.detach().float()
                return trans, yaws

            def measure() -> tuple:  # (penalty, task reward, task passed) of each room
                trans, yaws = placed()
                return penalty(trans, yaws).detach(), reward.gradient(batch)[0], task_results(task, batch)

            before.append(measure())
            for _ in range(args.steps):
                trans, yaws = placed()
                grad = reward.gradient(batch)[1]
                surrogate = (grad["translations"].double() * trans).sum() + (grad["yaws"].double() * yaws).sum()
                loss = penalty(trans, yaws).sum() - task_weight * surrogate
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                bar.update(len(trans0))
            after.append(measure())
            out += batch.to_layouts()
    save_layouts(out, args.out)
    for name, rows in (("before", before), ("after", after)):
        pen, val, ok = (np.concatenate([np.asarray(r[k]) for r in rows]) for k in range(3))
        print(f"{name}: {task.name} success {ok.mean():.1%}, task reward {val.mean():.3f}, penalty {pen.mean():.3f}")
    print(f"wrote {args.out} ({len(out)} rooms)")


if __name__ == "__main__":
    main()
