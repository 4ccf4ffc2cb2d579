"""Could a room pass wheelchair with its own furniture, each object placed anywhere on its floor? The greedy layout
search of ``layout_search.py`` (no network, no gradient), scored by the checker's two halves (the turning disk
by a bed 2, then the share of ground objects a wheelchair reaches). Classes, sizes and heights are kept, so it bounds
from below what an adapter that only moves and turns (``adapt: [position, yaw]``) could reach on these rooms: a
greedy search misses layouts that need two objects moved at once.

    .venv/bin/python research/wheelchair_search.py SCENES.json --out SEARCHED.json [--rooms 100 --grid 0.25]
    .venv/bin/python research/wheelchair_search.py SCENES.json --out NEAR.json --radius 0.2 --grid 0.05 --sweeps 1
    .venv/bin/python research/wheelchair_failures.py sampled=SCENES.json searched=SEARCHED.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from layout_search import search_room, wheelchair_score  # noqa: E402
from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64  # noqa: E402


def main(argv=None) -> None:
    from tqdm import tqdm

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="bedrooms (neutral JSON), e.g. stage 1's samples")
    parser.add_argument("--out", required=True, help="where to write the rearranged rooms")
    parser.add_argument("--rooms", type=int, help="only the first N rooms")
    parser.add_argument("--grid", type=float, default=0.25, help="spacing (m) of the placements tried")
    parser.add_argument("--sweeps", type=int, default=2, help="passes over the room's objects")
    parser.add_argument("--radius", type=float,
                        help="move each object at most this far (m) a sweep, in its own turn: how much of the task a "
                             "more precise placement of the same layout would pass")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    layouts = load_layouts(args.scenes, "bedroom")[:args.rooms]
    out, before, after = [], [], []
    for lay in tqdm(layouts, desc="rooms searched", unit="room"):
        room = batch_float64([lay])
        before.append(wheelchair_score(room)[0])
        room = search_room(room, "wheelchair", args.grid, args.sweeps, radius=args.radius)
        after.append(wheelchair_score(room)[0])
        out += room.to_layouts()
    save_layouts(out, args.out)
    before, after = np.array(before), np.array(after)
    print(f"{len(out)} rooms: wheelchair passes {np.mean(before >= 3):.1%} -> {np.mean(after >= 3):.1%}; "
          f"turning disk {np.mean(before >= 2):.1%} -> {np.mean(after >= 2):.1%}; wrote {args.out}")


if __name__ == "__main__":
    main()
