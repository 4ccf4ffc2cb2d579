"""``iarcs demo``: the first thing a new user sees work, offline, on a CPU, in about 9 minutes.

It takes the shipped small bedroom prior and its shipped stage-1 adapter (DDPO on the universal rewards),
has the offline planner write a reward program for one paper task, runs a short stage 2 (DDPO from the
stage-1 adapter with the task reward added, reflecting on the reward every 10 epochs), and ends with a
report: the prior, stage 1 and stage 2 sampled on the same held-out floor plans, the metrics table with
the task's success rate (its hand-written checker), before/after renders, the reward program and its
reflections. An interrupted demo resumes its training where it stopped.
"""

from __future__ import annotations

import json
from pathlib import Path

TASKS_DIR = Path(__file__).resolve().parents[1]


def register(sub) -> None:
    p = sub.add_parser("demo", help="stage 2 for one task with the offline planner, from the shipped prior and "
                                    "stage-1 adapter, then a report (about 9 minutes on 2 cores)")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--task", default="reach_1m",
                   help="paper task: reach_1m (default), tv_from_bed, study_zone, two_nightstands, wheelchair")
    p.add_argument("--epochs", type=int, default=100, help="stage-2 epochs (default 100, about 10 minutes on 2 cores)")
    p.add_argument("--num-scenes", type=int, default=64, help="scenes per row of the report (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    from agents.train import ADAPTERS_DIR, load_stage1_policy, load_train_config, run
    from experiments.cli import CLIError
    from experiments.commands.generate import (compare_variants, generation_floors, picture_table,
                                               program_section, write_comparison)
    from iarcs_env.tasks import get_task

    if args.num_scenes < 1 or args.epochs < 1:
        raise CLIError("--num-scenes and --epochs must be positive")
    task = get_task(args.task)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"1/3 stage 2 for {task.name!r}: \"{task.prompt}\"\n    the offline planner writes the reward; DDPO "
          f"trains a LoRA adapter from the shipped stage-1 adapter for {args.epochs} epochs ...")
    cfg = load_train_config(TASKS_DIR / f"task_{task.name}.yaml", out=str(out / "train"), epochs=args.epochs,
                            seed=args.seed)
    run(cfg)
    print(f"2/3 sampling {args.num_scenes} bedrooms on held-out floor plans: prior, stage 1, stage 2 ...")
    policy = load_stage1_policy("bedroom")
    policy.load_adapter(out / "train" / ADAPTERS_DIR / cfg.adapter, "stage2")
    floors = generation_floors("bedroom", args.num_scenes, args.seed)
    rows = compare_variants(policy, floors, args.seed, [("prior", None), ("stage 1", "stage1"), ("stage 2", "stage2")],
                            task.name)
    print("3/3 evaluating and rendering ...")
    table, pictures = write_comparison(out, rows, task.name)
    memory = json.loads((out / "train" / "reward_memory.json").read_text())
    first = memory["entries"][0]["proposal"]
    final = json.loads((out / "train" / "reward" / "proposal.json").read_text())
    report = [f"# iARCS demo: {task.prompt}", "",
              f"Stage 2 ({args.epochs} epochs, offline planner) from the shipped prior and stage-1 adapter; "
              f"{args.num_scenes} bedrooms per row on the same held-out floor plans with the same seed. Task "
              f"success is the hand-written checker `{task.name}` (iarcs_env/tasks.py), never the reward itself.",
              "", *table, "", picture_table(rows, pictures), "", *program_section(first),
              "## Reflections", "", *reflection_lines(memory)]
    if final["code"] != first["code"]:
        report += ["", "### The program in use at the end", "", "```python", final["code"].rstrip(), "```"]
    (out / "report.md").write_text("\n".join(report) + "\n")
    print("\n" + "\n".join(table) + "\n")
    print(f"renders: {', '.join(str(p) for p in pictures)}\nreport:  {out / 'report.md'}\n"
          f"TensorBoard: tensorboard --logdir {out / 'train' / 'tb'}")
    return 0


def reflection_lines(memory: dict) -> list[str]:
    """One line per reflection of the reward evolution memory: when, the verdict and the agent's notes."""
    lines = []
    for e in memory["entries"]:
        if e["kind"] != "reflect":
            continue
        verdict = "accepted" if e["accepted"] else f"rejected ({e['message']})"
        notes = e["proposal"].get("notes") or "no change"
        lines.append(f"- epoch {e['epoch']} ({verdict}): {notes}")
    return lines or ["- none (the run was shorter than one reflection period)"]
