"""Why scenes fail reach_1m: for each scene file, the pass rate and, over the failing scenes, how many hold a
support surface of each class whose top is above 1.0 m (a scene can count for several classes) and how many
hold no support surface at all.

    .venv/bin/python research/reach_failures.py data=FLOORS.json stage1=STAGE1.json reach=REACH.json

Each argument is ``NAME=FILE`` (or a file, named by its stem): a neutral-JSON bedroom scene file.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.relations import CLASS_GROUPS  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402

TOP = 1.0  # the checker's reach limit (m)


def failures(layouts) -> tuple[float, int, int, Counter]:
    """(pass rate, failing scenes, failing scenes without a support surface, failing scenes by too-high class)."""
    support = set(CLASS_GROUPS["support_surface"])
    ok = task_results("reach_1m", layouts)
    too_high, bare = Counter(), 0
    for lay, passed in zip(layouts, ok):
        if passed:
            continue
        tops = lay.translations[:, 1] + lay.half_sizes[:, 1]
        bare += not any(label in support for label in lay.labels)
        too_high.update({label for label, top in zip(lay.labels, tops) if label in support and top > TOP + 1e-6})
    return float(ok.mean()), int((~ok).sum()), bare, too_high


def main(args: list[str]) -> None:
    if not args:
        sys.exit(__doc__)
    for arg in args:
        name, _, path = arg.rpartition("=")
        rate, failing, bare, too_high = failures(load_layouts(path, "bedroom"))
        classes = ", ".join(f"{label} {n}" for label, n in too_high.most_common(6))
        print(f"{name or Path(path).stem}: passes {100 * rate:.1f}%; of the {failing} failing scenes, {bare} hold no "
              f"support surface; top above {TOP} m: {classes}")


if __name__ == "__main__":
    main(sys.argv[1:])
