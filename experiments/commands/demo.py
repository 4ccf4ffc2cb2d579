"""``iarcs demo``: the first thing a new user sees work, offline on a CPU.

Today: the shipped small bedroom prior and its shipped stage-1 LoRA adapter (DDPO on the universal
rewards) sample scenes on the same held-out procedural floor plans; both are evaluated with the paper's
metrics next to the procedural data the prior was trained on, and rendered with collisions, out-of-bound
objects and unreachable floor marked. (Stage 2 joins the demo when it lands.)
"""

from __future__ import annotations

import time
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("demo", help="sample, evaluate and render bedrooms with the shipped prior, offline")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--num-scenes", type=int, default=64, help="scenes to sample (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    import contextlib

    import torch

    from agents.train import load_stage1_policy
    from experiments.cli import CLIError
    from experiments.commands.evaluate import markdown_table
    from iarcs_env.datasets import save_layouts
    from iarcs_env.datasets.procedural import generate_layouts
    from iarcs_env.env import default_floors
    from iarcs_env.metrics import evaluate_layouts
    from iarcs_env.render import image_grid, render_layout, save_image

    if args.num_scenes < 1:
        raise CLIError(f"--num-scenes must be positive, got {args.num_scenes}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("1/4 loading the shipped bedroom prior and its stage-1 adapter ...")
    policy = load_stage1_policy("bedroom")
    floors = default_floors("bedroom", count=args.num_scenes, seed=12345 + args.seed)
    print(f"2/4 sampling {args.num_scenes} bedrooms (20 DDIM steps) on held-out floor plans, without and with "
          "the adapter ...")
    runs = {}
    for name, context in (("prior", policy.base_policy), ("stage 1", contextlib.nullcontext)):
        t0 = time.perf_counter()
        with context():
            scenes = policy.sample(floors, generator=torch.Generator().manual_seed(args.seed))
        runs[name] = (scenes.to_layouts(), time.perf_counter() - t0)
    reference = generate_layouts("bedroom", 500, seed=0)
    print("3/4 evaluating (collisions, out of bound, reachability, walkability) ...")
    table = markdown_table(evaluate_layouts(reference, reference=reference), "procedural training data").splitlines()
    pictures = []
    for name, (samples, elapsed) in runs.items():
        res = evaluate_layouts(samples, reference=reference, keep_scenes=True, keep_masks=True)
        table.append(markdown_table(res, f"{name} samples ({elapsed:.1f} s)").splitlines()[-1])
        slug = name.replace(" ", "")
        save_layouts(samples, out / f"{slug}.json", generator=f"iarcs demo: {name}", seed=args.seed)
        shown = range(min(16, len(samples)))
        grid = image_grid([render_layout(samples[i], overlays=res["scenes"][i].overlays()) for i in shown], cols=4,
                          titles=[f"{name} {i}" for i in shown])
        pictures.append(save_image(grid, out / f"{slug}.png"))
    print("4/4 rendering ...")
    save_image(image_grid([render_layout(r) for r in reference[:16]], cols=4), out / "training_data.png")
    report = "\n".join([
        "# iARCS demo", "", "\n".join(table), "",
        f"{args.num_scenes} bedrooms per row, sampled on the same held-out floor plans with the same seed.", "",
        "| prior | stage 1 (LoRA, universal rewards) |", "|---|---|",
        f"| ![prior]({pictures[0].name}) | ![stage 1]({pictures[1].name}) |", "",
        "Red: colliding objects; magenta: out of bound; orange: floor the agent (radius 0.3 m) cannot reach "
        "from the largest free region.", ""])
    (out / "report.md").write_text(report)
    print("\n" + "\n".join(table) + "\n")
    print(f"pictures: {', '.join(str(p) for p in pictures)} (issues marked), {out / 'training_data.png'}\n"
          f"report:   {out / 'report.md'}")
    return 0
