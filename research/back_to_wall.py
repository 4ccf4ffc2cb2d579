"""How far a class's objects stand from the wall behind them: the distance (m) from the midpoint of each object's
back edge to the floor's boundary, per scene file (the wardrobe_back_to_wall relation counts 0.2 m or less).

    .venv/bin/python research/back_to_wall.py CLASS NAME=S.json [NAME=S.json ...] [--room bedroom]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from shapely.geometry import Point, Polygon

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.relation_fidelity import WALL_TOLERANCE  # noqa: E402


def back_distances(layouts, label: str) -> np.ndarray:
    """Distances (m) of the back-edge midpoints of every ``label`` object of ``layouts`` from their floor's boundary."""
    out = []
    for lay in layouts:
        boundary = Polygon(np.asarray(lay.floor.vertices)).exterior
        for i, name in enumerate(lay.labels):
            if name == label:
                x, z, yaw, depth = lay.translations[i, 0], lay.translations[i, 2], lay.yaws[i], lay.half_sizes[i, 2]
                out.append(boundary.distance(Point(x - depth * math.sin(yaw), z - depth * math.cos(yaw))))
    return np.array(out)


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
        print(f"{name or path}: {len(d)} {args.label}, back within {WALL_TOLERANCE} m of a wall "
              f"{np.mean(d <= WALL_TOLERANCE):.0%}, median {np.median(d):.2f} m, 75th percentile "
              f"{np.percentile(d, 75):.2f} m")


if __name__ == "__main__":
    main()
