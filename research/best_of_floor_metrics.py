"""How much a floor's samplings differ in collisions and walkways: from ``iarcs evaluate`` reports of several
samplings of the same floors, Col_obj and R_reach pooled over all of them against each floor's best sampling (the
fewest colliding plus unreachable ground objects per ground object). A wide gap is room for a policy that learns
each floor's best of k (``ddpo.best_of_floor_weight``); none, and drawing on the best rollouts cannot help. The
ground objects per room tell whether the best is a better arrangement or an emptier room (which an adapter that
keeps the classes cannot copy): the last line picks each floor's sampling with the fewest ground objects, blind to
collisions and walkways. Samplings of the same objects on each floor: ``research/same_objects_samplings.py``.

    iarcs evaluate --scenes S.json --features none --out S_report.json      # for each sampling of the floors
    .venv/bin/python research/best_of_floor_metrics.py S0_report.json S1_report.json ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", help="evaluate reports of samplings of the same floors, in one order")
    args = parser.parse_args(argv)
    scenes = [json.loads(Path(path).read_text())["per_scene"] for path in args.reports]
    if len({len(s) for s in scenes}) != 1:
        raise SystemExit(f"the reports hold different numbers of scenes ({', '.join(str(len(s)) for s in scenes)}): "
                         f"give samplings of the same floors")
    # (k, floors) counts: ground objects, colliding, unreachable
    ground = np.array([[s["ground_objects"] for s in run] for run in scenes], dtype=float)
    colliding = np.array([[len(s["colliding"]) for s in run] for run in scenes], dtype=float)
    unreachable = np.array([[len(s["unreachable_objects"]) for s in run] for run in scenes], dtype=float)
    floors = np.arange(ground.shape[1])

    def figures(pick) -> str:
        g, c, u = ground[pick], colliding[pick], unreachable[pick]
        return (f"Col_obj {c.sum() / g.sum():.1%}, R_reach {1 - u.sum() / g.sum():.1%}, "
                f"{g.mean():.2f} ground objects per room")

    print(f"{ground.shape[1]} floors, {len(scenes)} samplings each")
    print(f"all samplings: {figures(slice(None))}")
    print(f"each floor's best: {figures((((colliding + unreachable) / np.maximum(ground, 1)).argmin(0), floors))}")
    print(f"each floor's fewest ground objects: {figures((ground.argmin(0), floors))}")


if __name__ == "__main__":
    main()
