"""What stops the wheelchair task: for each bedroom scene file, the share of rooms passing each half of the
checker (every ground object reachable by a 0.45 m agent; a 0.75 m turning disk on free floor within 0.5 m of a
bed) and both, the classes of the objects the agent cannot reach, and the pass rate again with every nightstand
(then also every wardrobe) taken out of each room: an upper bound on what removing them could buy; and the pass
rate for a wheelchair and turning disk 5 and 10 cm wider, which says how far the passing rooms are from the limit.

    .venv/bin/python research/wheelchair_failures.py data=FLOORS.json stage1=STAGE1.json \
        real=../shared/data/3dfront/bedroom_val.json

Each argument is ``NAME=FILE`` (or a file, named by its stem): a neutral-JSON bedroom scene file.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env import tasks  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64  # noqa: E402
from iarcs_env.scene import Layout  # noqa: E402


def without(lay: Layout, classes: set[str]) -> Layout:
    """``lay`` with the objects of ``classes`` taken out."""
    keep = [i for i, label in enumerate(lay.labels) if label not in classes]
    return Layout(lay.room_type, lay.floor, [lay.labels[i] for i in keep], lay.translations[keep],
                  lay.half_sizes[keep], lay.yaws[keep], lay.id, lay.ceiling_height, [lay.extras[i] for i in keep])


def halves(layouts: list[Layout], chunk: int = 100, margin: float = 0.0) -> dict:
    """Per room: all ground objects reached, turning disk found; and the classes of unreached objects (for a
    wheelchair and disk ``margin`` m wider)."""
    reached_all, disk, unreached = [], [], Counter()
    for s in range(0, len(layouts), chunk):
        part = layouts[s:s + chunk]
        batch = batch_float64(part)
        ground = batch.ground_mask
        reached, found = tasks.wheelchair_parts(batch, margin)
        reached_all.append((reached | ~ground).all(1).cpu().numpy())
        disk.append(np.asarray(found))
        for k, lay in enumerate(part):
            unreached.update(lay.labels[i] for i in np.nonzero((ground[k] & ~reached[k]).cpu().numpy())[0])
    return {"reach": np.concatenate(reached_all), "disk": np.concatenate(disk), "unreached": unreached}


def main(args: list[str]) -> None:
    if not args:
        sys.exit(__doc__)
    for arg in args:
        name, _, path = arg.rpartition("=")
        layouts = load_layouts(path, "bedroom")
        n = len(layouts)
        h = halves(layouts)
        top = ", ".join(f"{c} {k / n:.2f}" for c, k in h["unreached"].most_common(4))
        no_stands = tasks.task_results("wheelchair", [without(lay, {"nightstand"}) for lay in layouts]).mean()
        no_both = tasks.task_results("wheelchair", [without(lay, {"nightstand", "wardrobe"}) for lay in layouts]).mean()
        by_margin = {margin: halves(layouts, margin=margin) for margin in (0.05, 0.1)}
        wider = ", ".join(f"{m * 100:.0f} cm {np.mean(w['reach'] & w['disk']):.1%}" for m, w in by_margin.items())
        print(f"{name or Path(path).stem} ({n} rooms): passes {np.mean(h['reach'] & h['disk']):.1%} (every object "
              f"reached {h['reach'].mean():.1%}, turning disk {h['disk'].mean():.1%}); unreached per room: {top}; "
              f"passes without nightstands {no_stands:.1%}, without nightstands and wardrobes {no_both:.1%}; "
              f"passes with a wider wheelchair and disk: {wider}")


if __name__ == "__main__":
    main(sys.argv[1:])
