"""What adding a task's objects to only a share of the rooms would give: task success against class KL to the data.

    .venv/bin/python research/required_share.py TASK DATA.json STAGE1.json GIVEN.json [--shares 1 0.8 0.6 0.4]

STAGE1.json and GIVEN.json are the same floors sampled by stage 1 and by stage 1 with the task's objects given
(``research/required_objects.py``); DATA.json holds the data rooms of those floors. For each share p, a random p of
the rooms (seed 0) is taken from GIVEN, the rest from STAGE1, and the mixture's task success and class KL are
printed: an estimate, before any training, of the share that meets both a success target and a class-KL limit.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import class_kl  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402


def mixtures(task: str, data, stage1, given, shares, seed: int = 0) -> list[tuple[float, float, float]]:
    """(share, success, class KL) of rooms taken from ``given`` with probability share, else from ``stage1``."""
    if len(stage1) != len(given):
        raise ValueError(f"the two scene files must sample the same floors: {len(stage1)} against {len(given)} rooms")
    passes_stage1 = task_results(task, stage1).astype(bool)
    passes_given = task_results(task, given).astype(bool)
    rows = []
    for share in shares:
        pick = np.random.default_rng(seed).random(len(given)) < share
        mixed = [g if k else s for g, s, k in zip(given, stage1, pick)]
        rows.append((share, float(np.where(pick, passes_given, passes_stage1).mean()), class_kl(data, mixed)))
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("task")
    p.add_argument("data")
    p.add_argument("stage1")
    p.add_argument("given")
    p.add_argument("--shares", type=float, nargs="+", default=[1.0, 0.8, 0.7, 0.6, 0.5, 0.4])
    p.add_argument("--room", default="bedroom")
    args = p.parse_args()
    files = [load_layouts(f, args.room) for f in (args.data, args.stage1, args.given)]
    for share, success, kl in mixtures(args.task, *files, args.shares):
        print(f"{args.task}: objects given in {share:.0%} of the rooms: success {success:.1%}, class KL {kl:.3f}")


if __name__ == "__main__":
    main()
