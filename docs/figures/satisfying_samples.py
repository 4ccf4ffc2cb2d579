"""Scenes of the shipped stage-1 adapter that pass each paper task's checker, found by rejection sampling
(``iarcs sample --satisfying``), four per task at one metric scale, with how many draws it took.

    .venv/bin/python docs/figures/satisfying_samples.py [--floors 16] [--max-draws 200] [--seed 777]

Writes docs/figures/satisfying_samples.png.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from agents.train import load_stage1_policy
from iarcs_env.env import default_floors
from iarcs_env.render import image_grid, palette_legend, render_layout
from iarcs_env.tasks import TASKS, sample_satisfying

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--floors", type=int, default=16, help="held-out floor plans tried per task (default 16)")
    ap.add_argument("--max-draws", type=int, default=200, help="draws per floor plan (default 200)")
    ap.add_argument("--seed", type=int, default=777, help="seed of the floor plans and the sampler")
    args = ap.parse_args()
    policy = load_stage1_policy("bedroom")
    floors = default_floors("bedroom", count=args.floors, seed=args.seed)
    extent, size, panels, classes = 3.6, 200, [], set()
    for task in TASKS:
        gen = torch.Generator().manual_seed(args.seed)
        kept, drawn, passed = sample_satisfying(
            lambda idx: policy.sample([floors[i] for i in idx], generator=gen).to_layouts(), len(floors), task,
            args.max_draws, batch_size=256)
        shown = [lay for lay in kept if lay is not None][:4]
        classes |= {c for lay in shown for c in lay.labels}
        images = [render_layout(lay, size=size, extent=extent) for lay in shown]
        images += [np.full((size, size, 3), 255, np.uint8)] * (4 - len(shown))  # fewer than 4 found: blanks
        grid = image_grid(images, cols=4)
        title = (f"{task}: {int(passed.sum())} of {int(drawn.sum())} draws passed; "
                 f"{sum(lay is not None for lay in kept)} of {len(floors)} floor plans found one")
        head = Image.new("RGB", (grid.shape[1], 18), (255, 255, 255))
        ImageDraw.Draw(head).text((6, 3), title, fill=(0, 0, 0), font=ImageFont.load_default())
        panels.append(np.concatenate([np.asarray(head), grid], 0))
        print(title)
    body = np.concatenate(panels, 0)
    legend = palette_legend(sorted(classes), width=150)
    canvas = np.full((max(body.shape[0], legend.shape[0]), body.shape[1] + legend.shape[1], 3), 255, np.uint8)
    canvas[: body.shape[0], : body.shape[1]] = body
    canvas[: legend.shape[0], body.shape[1]:] = legend
    out = HERE / "satisfying_samples.png"
    Image.fromarray(canvas).save(out)
    print(f"wrote {out} ({extent * 2:.1f} m wide views; a dark tick marks each object's front)")


if __name__ == "__main__":
    main()
