"""What a task's own objects cost in class KL: the class-frequency KL to the data (``KL_class`` of ``iarcs evaluate
--reference``) of scenes, then of the same scenes with ``CLASS`` topped up to ``COUNT`` objects in the first 70%
and in all of the rooms (nothing else changed). A task adapter that only added what its task needs would sit near
these figures; one far above them changed other classes too.

    .venv/bin/python research/class_kl_top_up.py FLOORS.json STAGE1.json tv_stand 1
    .venv/bin/python research/class_kl_top_up.py FLOORS.json STAGE1.json nightstand 2
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import class_kl  # noqa: E402
from iarcs_env.scene import Layout  # noqa: E402


def topped_up(lay: Layout, cls: str, count: int) -> Layout:
    """``lay`` with objects of ``cls`` added until it holds ``count`` (their geometry does not enter the KL)."""
    extra = max(0, count - lay.labels.count(cls))
    if not extra:
        return lay
    return Layout(lay.room_type, lay.floor, lay.labels + [cls] * extra,
                  np.vstack([lay.translations, np.zeros((extra, 3))]),
                  np.vstack([lay.half_sizes, np.full((extra, 3), 0.2)]), np.concatenate([lay.yaws, np.zeros(extra)]))


def main(args: list[str]) -> None:
    if len(args) != 4:
        sys.exit(__doc__)
    reference, scenes, cls, count = load_layouts(args[0]), load_layouts(args[1]), args[2], int(args[3])
    print(f"class KL to the data: as they are {class_kl(reference, scenes):.3f}", end="")
    for share in (0.7, 1.0):
        k = int(share * len(scenes))
        changed = [topped_up(lay, cls, count) if i < k else lay for i, lay in enumerate(scenes)]
        print(f"; {cls} topped up to {count} in the first {share:.0%} of the rooms {class_kl(reference, changed):.3f}",
              end="")
    print()


if __name__ == "__main__":
    main(sys.argv[1:])
