"""How a sampler's success depends on the floor plan: two independent draws on the same floors (two sampling
seeds), and how often the second passes where the first passed or failed. A rejection sampler's acceptance
(passed / drawn) falls far below its one-draw success when failures stick to floors, because the retries pile up
there (issue 38's cost table: two_nightstands' adapter).

    iarcs sample --floors FLOORS.json --num-scenes 1000 --seed 0 --adapter two_nightstands --out A.json
    iarcs sample --floors FLOORS.json --num-scenes 1000 --seed 1 --adapter two_nightstands --out B.json
    .venv/bin/python research/repeat_draws.py two_nightstands A.json B.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402


def repeat_rates(first: np.ndarray, second: np.ndarray) -> dict:
    """Pass rates of two draws per floor (bool arrays, floor by floor): each draw's, the second's given the first
    passed or failed, and the share of floors failing both."""
    if first.shape != second.shape:
        raise ValueError(f"the two files hold {len(first)} and {len(second)} scenes: sample the same floors twice")
    return {"first": first.mean(), "second": second.mean(), "second | first passed": second[first].mean(),
            "second | first failed": second[~first].mean(), "both failed": (~first & ~second).mean()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("task", help="reach_1m, tv_from_bed, study_zone, two_nightstands or wheelchair")
    parser.add_argument("first", help="layout file of the first draw")
    parser.add_argument("second", help="layout file of the second draw, on the same floors in the same order")
    args = parser.parse_args()
    draws = [task_results(args.task, load_layouts(path, "bedroom")) for path in (args.first, args.second)]
    for name, rate in repeat_rates(*draws).items():
        print(f"{name}: {rate:.1%}")


if __name__ == "__main__":
    main()
