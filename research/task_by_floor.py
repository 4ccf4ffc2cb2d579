"""How often each floor passes a task over several samplings of the same floors: where the samplings disagree, a
policy that learns each floor's best of k (``ddpo.best_of_floor_weight``) has room to gain; a floor that never
passes needs more than that.

    .venv/bin/python research/task_by_floor.py TASK S0.json S1.json ... [--room bedroom]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("task")
    parser.add_argument("files", nargs="+", help="scene files sampled on the same floors, in the same order")
    parser.add_argument("--room", default="bedroom")
    args = parser.parse_args(argv)
    ok = np.array([task_results(args.task, load_layouts(f, args.room)) for f in args.files]).astype(bool)
    passing = ok.sum(0)
    print(f"{args.task}: {ok.mean():.1%} of {ok.size} rooms pass; floors by how many of the {len(args.files)} "
          f"samplings pass:")
    for k, count in enumerate(np.bincount(passing, minlength=len(args.files) + 1)):
        print(f"  {k}: {count} floors")
    print(f"floors where at least one sampling passes (each floor's best of {len(args.files)}): "
          f"{(passing > 0).mean():.1%}")


if __name__ == "__main__":
    main()
