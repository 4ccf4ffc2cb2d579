"""What an adapter did to each class of object, against the rooms it started from: per class, how far its objects
moved on the floor in the rooms that hold the same objects both ways (an adapter sampled on the prior's noise, as
``iarcs sample`` does with the same floors and seed), and how many of them are unreachable (R_reach) and out of bound
(R_out) in each; then where the walkway went: the rooms binned by the base room's R_walkable (the share of free floor
in its largest region), with the unreachable objects base -> run in each bin and the rooms the run splits (R_walkable
from WHOLE or more down under SPLIT). Reads ``iarcs evaluate`` reports (their ``per_scene`` lists and
``scenes_file``), in pairs.

    .venv/bin/python research/object_moves.py PRIOR_S0_report.json RUN_S0_report.json [PRIOR_S1 RUN_S1 ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402


def report_rooms(report_path: str | Path):
    """(layouts, per-scene entries) of an ``iarcs evaluate`` report; its scene file is read relative to the report."""
    report_path = Path(report_path)
    report = json.loads(report_path.read_text())
    scenes = Path(report["scenes_file"])
    if not scenes.is_absolute() and not scenes.exists():
        scenes = report_path.parent / scenes
    layouts = load_layouts(scenes, report["room_type"])
    if len(layouts) != len(report["per_scene"]):
        raise SystemExit(f"{report_path}: {len(report['per_scene'])} scenes scored but {scenes} holds {len(layouts)}")
    return layouts, report["per_scene"]


def object_moves(pairs) -> tuple[dict[str, dict], int]:
    """(per class, paired rooms) over ``pairs`` of (base, run) report paths. Per class: objects (base), mean and median
    move (m) in the paired rooms (the same labels both ways), unreachable and out-of-bound counts in base and run."""
    moves, paired = defaultdict(list), 0
    counts = {key: Counter() for key in ("objects", "unreachable_base", "unreachable_run", "out_base", "out_run")}
    for base_path, run_path in pairs:
        (base, base_scored), (run, run_scored) = report_rooms(base_path), report_rooms(run_path)
        if len(base) != len(run):
            raise SystemExit(f"{base_path} and {run_path} score different numbers of rooms: sample the same floors")
        for b, r, bs, rs in zip(base, run, base_scored, run_scored):
            counts["objects"].update(b.labels)
            for side, lay, scored in (("base", b, bs), ("run", r, rs)):
                counts[f"unreachable_{side}"].update(lay.labels[i] for i in scored["unreachable_objects"])
                counts[f"out_{side}"].update(lay.labels[i] for i in scored["out_of_bound"])
            if list(b.labels) == list(r.labels):
                paired += 1
                step = np.hypot(*(r.translations[:, [0, 2]] - b.translations[:, [0, 2]]).T)
                for label, d in zip(b.labels, step):
                    moves[label].append(float(d))
    return {c: {"objects": n, "mean_move": float(np.mean(moves[c])) if moves[c] else float("nan"),
                "median_move": float(np.median(moves[c])) if moves[c] else float("nan"),
                **{k: counts[k][c] for k in counts if k != "objects"}}
            for c, n in counts["objects"].most_common()}, paired


WALKABLE_BINS = (0.0, 0.6, 0.75, 0.85, 0.95, 1.0)
"""Bins of the base room's R_walkable for :func:`reach_by_walkable` (the last bin takes 0.95-1.0 inclusive)."""
WHOLE, SPLIT = 0.95, 0.9
"""A room whose R_walkable is at least WHOLE in the base and under SPLIT in the run is counted as split by the run."""


def reach_by_walkable(pairs) -> tuple[list[dict], int]:
    """(per bin of the base room's R_walkable: rooms, unreachable objects in base and run; rooms split) over ``pairs``
    of (base, run) report paths, room by room (the same floors and seed both ways)."""
    rows = [{"lo": lo, "hi": hi, "rooms": 0, "unreachable_base": 0, "unreachable_run": 0}
            for lo, hi in zip(WALKABLE_BINS[:-1], WALKABLE_BINS[1:])]
    split = 0
    for base_path, run_path in pairs:
        base, run = (json.loads(Path(p).read_text())["per_scene"] for p in (base_path, run_path))
        if len(base) != len(run):
            raise SystemExit(f"{base_path} and {run_path} score different numbers of rooms: sample the same floors")
        for b, r in zip(base, run):
            row = next(x for x in rows if b["R_walkable"] < x["hi"] or x is rows[-1])
            row["rooms"] += 1
            row["unreachable_base"] += len(b["unreachable_objects"])
            row["unreachable_run"] += len(r["unreachable_objects"])
            split += b["R_walkable"] >= WHOLE and r["R_walkable"] < SPLIT
    return rows, split


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", help="iarcs evaluate reports: BASE RUN [BASE RUN ...]")
    args = ap.parse_args(argv)
    if len(args.reports) % 2:
        ap.error("give the reports in pairs: BASE RUN [BASE RUN ...]")
    rows, paired = object_moves(list(zip(args.reports[::2], args.reports[1::2])))
    print(f"moves over the {paired} rooms that hold the same objects both ways")
    print("| class | objects | mean move (m) | median move (m) | unreachable | out of bound |")
    print("|---|---:|---:|---:|---:|---:|")
    for c, r in rows.items():
        print(f"| {c} | {r['objects']} | {r['mean_move']:.3f} | {r['median_move']:.3f} "
              f"| {r['unreachable_base']} -> {r['unreachable_run']} | {r['out_base']} -> {r['out_run']} |")
    lost = sum(r["unreachable_run"] - r["unreachable_base"] for r in rows.values())
    print(f"unreachable objects: {lost:+d} in all")
    bins, split = reach_by_walkable(list(zip(args.reports[::2], args.reports[1::2])))
    print("\n| the base room's R_walkable | rooms | unreachable objects |")
    print("|---|---:|---:|")
    for b in bins:
        print(f"| {b['lo']:.2f}-{b['hi']:.2f} | {b['rooms']} | {b['unreachable_base']} -> {b['unreachable_run']} |")
    print(f"rooms split by the run (R_walkable >= {WHOLE} -> < {SPLIT}): {split}")


if __name__ == "__main__":
    main()
