"""``iarcs demo``: the first thing a new user sees work (grows with the project)."""

from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("demo", help="generate, evaluate and render a small set of scenes, offline")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--num-scenes", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    from iarcs_env.datasets import save_layouts
    from iarcs_env.datasets.procedural import generate_layouts
    from iarcs_env.render import image_grid, render_layout, save_image

    out = Path(args.out)
    layouts = generate_layouts("bedroom", args.num_scenes, seed=args.seed, progress=True)
    path = save_layouts(layouts, out / "bedrooms.json")
    grid = save_image(image_grid([render_layout(l) for l in layouts], cols=4), out / "bedrooms.png")
    print(f"scenes: {path}\npictures: {grid}")
    return 0
