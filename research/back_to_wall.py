"""How far a class's objects stand from the wall behind them, per scene file: the distance (m) from the midpoint of
each object's back edge to the nearest floor boundary on its front-back axis (either way), the measure the wardrobe_back_to_wall relation
holds at 0.2 m or less (``iarcs_env.relation_fidelity``).

    .venv/bin/python research/back_to_wall.py CLASS NAME=S.json [NAME=S.json ...] [--room bedroom]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env import relation_fidelity as rf  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64  # noqa: E402


def back_distances(layouts, label: str, chunk: int = 100) -> np.ndarray:
    """Distances (m) of the back-edge midpoints of every ``label`` object of ``layouts`` from the wall behind them
    (absolute: a back poking through the wall counts as far as one short of it)."""
    out = []
    for s in range(0, len(layouts), chunk):
        scenes = rf._Scenes(batch_float64(layouts[s:s + chunk]))
        out.append(scenes.back.abs()[scenes.mask(label)].numpy())
    return np.concatenate(out)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("label", help="an object class, e.g. double_bed, wardrobe, tv_stand")
    parser.add_argument("files", nargs="+", help="NAME=FILE: scene files")
    parser.add_argument("--room", default="bedroom")
    args = parser.parse_args(argv)
    for item in args.files:
        name, _, path = item.rpartition("=")
        d = back_distances(load_layouts(path, args.room), args.label)
        if not len(d):
            print(f"{name or path}: no {args.label}")
            continue
        print(f"{name or path}: {len(d)} {args.label}, back within {rf.WALL_TOLERANCE} m of a wall "
              f"{np.mean(d <= rf.WALL_TOLERANCE):.0%}, median {np.median(d):.2f} m, 75th percentile "
              f"{np.percentile(d, 75):.2f} m")


if __name__ == "__main__":
    main()
