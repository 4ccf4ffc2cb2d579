"""Renders of 8 procedural and 8 real bedrooms side by side, at one metric scale, for a person to judge.

    .venv/bin/python docs/figures/side_by_side.py [--room bedroom] [--seed 0]

Writes docs/figures/<room>_procedural_vs_real.png. Needs ../shared/data/3dfront/<room>_val.json.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from iarcs_env.datasets import load_layouts
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.render import image_grid, palette_legend, render_layout

HERE = Path(__file__).resolve().parent
REAL = HERE.parents[2] / "shared" / "data" / "3dfront"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--room", default="bedroom", choices=["bedroom", "livingroom"])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    real_path = REAL / f"{args.room}_val.json"
    if not real_path.exists():
        raise SystemExit(f"real layouts not found at {real_path}; they are kept outside the repository")
    rng = np.random.default_rng(args.seed)
    real = load_layouts(real_path)
    real = [real[i] for i in rng.choice(len(real), 8, replace=False)]
    gen = generate_layouts(args.room, 8, seed=args.seed)
    extent = 3.6 if args.room == "bedroom" else 5.0  # half width of every view, metres: one scale for all
    size = 224
    panels = []
    for name, layouts in (("procedural (iarcs data generate, seed %d)" % args.seed, gen), ("real 3D-FRONT (val)", real)):
        grid = image_grid([render_layout(l, size=size, extent=extent) for l in layouts], cols=4,
                          titles=[l.id.split(":")[-1] for l in layouts])
        head = Image.new("RGB", (grid.shape[1], 18), (255, 255, 255))
        ImageDraw.Draw(head).text((6, 3), name, fill=(0, 0, 0), font=ImageFont.load_default())
        panels.append(np.concatenate([np.asarray(head), grid], 0))
    body = np.concatenate(panels, 1)
    classes = sorted({c for l in gen + real for c in l.labels})
    legend = palette_legend(classes, width=150)
    canvas = np.full((max(body.shape[0], legend.shape[0]), body.shape[1] + legend.shape[1], 3), 255, np.uint8)
    canvas[: body.shape[0], : body.shape[1]] = body
    canvas[: legend.shape[0], body.shape[1]:] = legend
    out = HERE / f"{args.room}_procedural_vs_real.png"
    Image.fromarray(canvas).save(out)
    print(f"wrote {out} ({extent * 2:.1f} m wide views; a dark tick marks each object's front)")


if __name__ == "__main__":
    main()
