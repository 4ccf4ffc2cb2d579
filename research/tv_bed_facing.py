"""Why tv_from_bed fails: its success by how far the bed's centre is from the wall it faces (the floor polygon
along the bed's forward ray), for each scene file's first bed-TV stand pair.

    .venv/bin/python research/tv_bed_facing.py NAME=S.json [NAME=S.json ...]
    .venv/bin/python research/tv_bed_facing.py --same-floors S0.json S1.json ...   # samplings of the same floors

With ``--same-floors``, the floors by how many of the samplings face their bed to less than 2.3 m of floor, and the
success of the samplings whose facing differs from floor to floor, by the way they face: whether the floor or the
sampling's noise chooses.

A room whose bed faces a wall less than about 2.3 m away cannot pass by moving furniture (TV stand centre 2 m
from the bed's, inside the room): only a bed turned towards the room's long side can.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from shapely.geometry import LineString, Polygon

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402

NARROW = 2.3
"""m of floor ahead of the bed under which tv_from_bed nearly never passes."""
BANDS = [(0.0, 2.0), (2.0, 2.3), (2.3, 2.6), (2.6, 3.0), (3.0, math.inf)]


def bed_tv_distance(layout) -> float:
    """Centre distance (m, on the floor) of the room's first bed and first TV stand."""
    i = next(k for k, c in enumerate(layout.labels) if c.endswith("bed"))
    j = layout.labels.index("tv_stand")
    return float(np.hypot(*(layout.translations[i, 0:3:2] - layout.translations[j, 0:3:2])))


def room_ahead(layout) -> float | None:
    """Metres of floor ahead of the room's first bed (from its centre along its forward direction), None
    without a bed and a TV stand."""
    beds = [i for i, c in enumerate(layout.labels) if c.endswith("bed")]
    if not beds or "tv_stand" not in layout.labels:
        return None
    i = beds[0]
    x, z, yaw = float(layout.translations[i, 0]), float(layout.translations[i, 2]), float(layout.yaws[i])
    ray = LineString([(x, z), (x + 20 * math.sin(yaw), z + 20 * math.cos(yaw))])
    inside = ray.intersection(Polygon(np.asarray(layout.floor.vertices)))
    return 0.0 if inside.is_empty else float(inside.length)


def bands(layouts) -> list[tuple[float, float, int, float, int, int]]:
    """(from m, to m, rooms, success, failing rooms with the TV stand under 2 m, over 4 m) per band of the floor
    ahead of the bed."""
    ok = task_results("tv_from_bed", layouts).astype(bool)
    ahead = [room_ahead(lay) for lay in layouts]
    rows = []
    for lo, hi in BANDS:
        pick = [k for k, a in enumerate(ahead) if a is not None and lo <= a < hi]
        gaps = [bed_tv_distance(layouts[k]) for k in pick if not ok[k]]
        rows.append((lo, hi, len(pick), float(ok[pick].mean()) if pick else float("nan"),
                     sum(g < 2 for g in gaps), sum(g > 4 for g in gaps)))
    return rows


def long_side(layout) -> float:
    """The longer side (m) of the floor's smallest enclosing rectangle."""
    x, z = Polygon(np.asarray(layout.floor.vertices)).minimum_rotated_rectangle.exterior.xy
    return float(np.hypot(np.diff(x), np.diff(z))[:2].max())


def same_floors(paths) -> None:
    """Print how the samplings ``paths`` (scene files of the same floors, in the same order) face their beds."""
    ahead, ok = [], []
    for path in paths:
        layouts = load_layouts(path, "bedroom")
        ahead.append([room_ahead(lay) or 0.0 for lay in layouts])
        ok.append(task_results("tv_from_bed", layouts).astype(bool))
    narrow, ok = np.array(ahead) < NARROW, np.array(ok)
    count = narrow.sum(0)
    print(f"floors by how many of the {len(paths)} samplings face the bed to less than {NARROW} m of floor:")
    for k in range(len(paths) + 1):
        if (count == k).any():
            print(f"  {k}: {int((count == k).sum())} floors, tv_from_bed {ok[:, count == k].mean():.1%}")
    mixed = (count > 0) & (count < len(paths))
    print(f"floors whose samplings differ: tv_from_bed {ok[:, mixed][~narrow[:, mixed]].mean():.1%} where the bed "
          f"faces {NARROW} m or more, {ok[:, mixed][narrow[:, mixed]].mean():.1%} where less")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", help="NAME=FILE: bedroom scene files")
    parser.add_argument("--same-floors", action="store_true", help="the files are samplings of the same floors")
    args = parser.parse_args()
    if args.same_floors:
        same_floors([item.rpartition("=")[2] for item in args.files])
        return
    for item in args.files:
        name, _, path = item.rpartition("=")
        layouts = load_layouts(path, "bedroom")
        print(f"{name or path}: tv_from_bed {task_results('tv_from_bed', layouts).mean():.1%}")
        for lo, hi, n, rate, near, far in bands(layouts):
            print(f"  floor ahead of the bed {lo:.1f}-{hi:.1f} m: {n} rooms, {rate:.0%} pass; of the failing, "
                  f"TV stand under 2 m {near}, over 4 m {far}")
        long = np.mean([long_side(lay) >= 3.3 for lay in layouts])
        print(f"  floors 3.3 m long or more one way (a bed against a wall, a TV stand 2 m ahead): {long:.0%}")


if __name__ == "__main__":
    main()
