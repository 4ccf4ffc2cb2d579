"""The paper's two stage-2 ablations (issue 38, item 2), as task success against epochs with two training seeds:
(a) with and without reward reflection, on two_nightstands (reach_1m's, on the first stage-1 adapter:
docs/figures/ablation_reflection_stage1_collision.png); (b) two-stage (the task adapter starts
from the stage-1 adapter) against single-stage (universal and task rewards together, from the prior), on reach_1m;
and the two agents' programs (item 1): the offline planner's against the litellm agent's recorded answers
(experiments/llm_replay.py serving them while the arm trains).

    .venv/bin/python experiments/stage2_ablations.py run experiments/ablations/task_two_nightstands_no_reflection.yaml --seed 0
        [--epochs 100]   (each arm: experiments/task_<task>.yaml or experiments/ablations/task_<task>_*.yaml)
    .venv/bin/python experiments/stage2_ablations.py plot [--epochs 100]

``run`` trains CONFIG with the seed in ``out/ablation/<config>_s<seed>`` (resuming one that stopped). ``plot``
draws every run there into docs/figures/ablation_{reflection,stages,agents}.png (task
success and Col_obj on the run's 64 evaluation floors; each seed thin, their mean thick) and prints each run's
last, highest and lowest value.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "out" / "ablation"
FIGURES = ROOT / "docs" / "figures"
# figure -> (tasks, {arm label: config name pattern})
ABLATIONS = {
    "ablation_reflection": (["two_nightstands"],
                            {"with reflection": "task_{task}", "without reflection": "task_{task}_no_reflection"}),
    "ablation_stages": (["reach_1m"], {"two-stage": "task_{task}", "single-stage": "task_{task}_single_stage"}),
    "ablation_agents": (["reach_1m", "two_nightstands"],
                        {"offline planner": "task_{task}", "recorded LLM answers": "task_{task}_llm"}),
}


def run(config: Path, seed: int, epochs: int) -> Path:
    """Train ``config`` with ``seed`` for ``epochs`` into ``out/ablation/<config>_s<seed>``."""
    out = RUNS / f"{config.stem}_s{seed}"
    out.mkdir(parents=True, exist_ok=True)
    override = out.with_suffix(".yaml")
    override.write_text(f"base: {os.path.relpath(config.resolve(), override.parent)}\nseed: {seed}\n")
    iarcs = Path(sys.executable).parent / "iarcs"
    subprocess.run([str(iarcs), "train", "--config", str(override), "--epochs", str(epochs), "--out", str(out)],
                   cwd=ROOT, check=True)
    return out


def curve(run_dir: Path, key: str, epochs: int) -> tuple[list[int], list[float]]:
    """(epochs, ``key`` on the evaluation floors) of a run, up to ``epochs``."""
    from agents.config import read_jsonl

    rows = [r for r in read_jsonl(run_dir / "eval.jsonl") if r["epoch"] <= epochs]
    return [r["epoch"] for r in rows], [r[key] for r in rows]


COLOURS = {0: (31, 119, 180), 1: (255, 127, 14)}
W, H, LEFT, TOP, BOTTOM = 460, 320, 52, 30, 40


def draw_panel(draw, font, ox: int, oy: int, title: str, epochs: int,
               arms: dict[str, list[tuple[list, list]]]) -> None:
    """One panel at (``ox``, ``oy``): each arm's seeds thin, their mean thick, a rate 0-1 against epochs."""
    import numpy as np

    pw, ph = W - LEFT - 15, H - TOP - BOTTOM
    to_xy = lambda x, y: (ox + LEFT + x / epochs * pw, oy + TOP + ph - y * ph)  # noqa: E731
    draw.text((ox + LEFT, oy + 8), title, fill="black", font=font)
    draw.rectangle([ox + LEFT, oy + TOP, ox + LEFT + pw, oy + TOP + ph], outline="black")
    for k in range(6):  # success ticks 0, 0.2, ... 1
        _, py = to_xy(0, k / 5)
        draw.line([ox + LEFT - 4, py, ox + LEFT + pw, py], fill=(225, 225, 225))
        draw.text((ox + 8, py - 7), f"{k * 20}%", fill="black", font=font)
    for k in range(0, epochs + 1, max(10, epochs // 5)):
        px, _ = to_xy(k, 0)
        draw.line([px, oy + TOP + ph, px, oy + TOP + ph + 4], fill="black")
        draw.text((px - 8, oy + TOP + ph + 6), str(k), fill="black", font=font)
    draw.text((ox + LEFT + pw // 2 - 20, oy + H - 16), "epoch", fill="black", font=font)
    for a, (label, curves) in enumerate(arms.items()):
        colour = COLOURS[a]
        pale = tuple(int(c + (255 - c) * 0.6) for c in colour)
        for x, y in curves:
            draw.line([to_xy(*p) for p in zip(x, y)], fill=pale, width=1)
        if curves:
            n = min(len(x) for x, _ in curves)
            mean = np.mean([y[:n] for _, y in curves], 0)
            draw.line([to_xy(*p) for p in zip(curves[0][0][:n], mean)], fill=colour, width=3)
        ly = oy + TOP + 8 + 18 * a
        draw.line([ox + LEFT + 10, ly + 7, ox + LEFT + 35, ly + 7], fill=colour, width=3)
        seeds = f"{len(curves)} seed{'' if len(curves) == 1 else 's'}"
        draw.text((ox + LEFT + 42, ly), f"{label} ({seeds})", fill="black", font=font)


def plot(epochs: int) -> None:
    """Draw each ablation's figure (Pillow) and print every run's last, highest and lowest value."""
    from PIL import Image, ImageDraw, ImageFont

    try:
        font = ImageFont.load_default(size=13)
    except TypeError:  # an old Pillow: the bitmap font
        font = ImageFont.load_default()
    for figure, (tasks, arms) in ABLATIONS.items():
        image = Image.new("RGB", (W * len(tasks), 2 * H), "white")
        draw = ImageDraw.Draw(image)
        for i, task in enumerate(tasks):
            for row, (key, title) in enumerate([(f"task_success_{task}", f"{task}: task success"),
                                                ("Col_obj", f"{task}: Col_obj")]):
                curves = {}
                for label, pattern in arms.items():
                    runs = sorted(RUNS.glob(pattern.format(task=task) + "_s[0-9]*/eval.jsonl"))
                    curves[label] = [curve(r.parent, key, epochs) for r in runs]
                    for r, (x, y) in zip(runs, curves[label]):
                        print(f"{figure} {task} {label} {r.parent.name} {key}: {y[-1]:.1%} at epoch {x[-1]} "
                              f"(max {max(y):.1%}, min {min(y):.1%})")
                draw_panel(draw, font, i * W, row * H, f"{title}, 64 evaluation floors", epochs, curves)
        FIGURES.mkdir(parents=True, exist_ok=True)
        image.save(FIGURES / f"{figure}.png")
        print(f"-> {FIGURES / f'{figure}.png'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="train one arm with one seed")
    p.add_argument("config", type=Path,
                   help="the arm's config (experiments/task_*.yaml or experiments/ablations/task_*.yaml)")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--epochs", type=int, default=100, help="epochs (default 100)")
    p = sub.add_parser("plot", help="draw the figures from the runs in out/ablation")
    p.add_argument("--epochs", type=int, default=100, help="plot up to this epoch (default 100)")
    args = parser.parse_args()
    if args.command == "run":
        run(args.config, args.seed, args.epochs)
    else:
        plot(args.epochs)


if __name__ == "__main__":
    main()
