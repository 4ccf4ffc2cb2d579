"""Why chairs_at_dining_table holds or fails: in the rooms with a dining table and at least two chairs, the rate it
holds, chairs per room and at one table, and per chair the footprint gap to the nearest dining table (0: touching
or under it), the share within the relation's 0.6 m and the share of those facing the table
(``iarcs_env.relation_fidelity``'s tests), and the share standing ``PULLED_OUT`` m or more from their table (the data's
dining chairs never do; a chair pulled out that far closes the walkway behind it in a narrow room).

    .venv/bin/python research/chair_placement.py --room diningroom data=floors.json prior=prior.json run=S.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env import relation_fidelity as rf  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64  # noqa: E402

PULLED_OUT = 0.15
"""m: a chair this far or farther from its nearest dining table counts as pulled out."""


def chair_placement(layouts, chunk: int = 100) -> dict:
    gaps, facing, chairs, at_table = [], [], [], []
    for s in range(0, len(layouts), chunk):
        scenes = rf._Scenes(batch_float64(layouts[s:s + chunk]))
        table, chair = scenes.mask("dining_table"), scenes.mask(*rf.CHAIRS)
        pairs = scenes.pairs(table, chair)
        gap, looks = scenes.gap(pairs), scenes.looks_at(pairs)
        for k in range(len(table)):
            if not (table[k].any() and chair[k].sum() >= 2):
                continue
            chairs.append(int(chair[k].sum()))
            at_table.append(int(((gap[k] <= rf.CHAIR_GAP + rf.EPS) & looks[k]).sum(1).max()))
            tables = table[k].nonzero().squeeze(1)
            for j in chair[k].nonzero().squeeze(1):
                i = tables[gap[k, tables, j].argmin()]
                gaps.append(float(gap[k, i, j]))
                facing.append(bool(looks[k, i, j]))
    gaps, facing, near = np.array(gaps), np.array(facing), np.array(gaps) <= rf.CHAIR_GAP + rf.EPS
    return {"rooms": len(chairs), "holds": float(np.mean(np.array(at_table) >= 2)), "chairs": float(np.mean(chairs)),
            "at_table": float(np.mean(at_table)), "touching": float(np.mean(gaps <= 1e-6)),
            "pulled_out": float(np.mean(gaps >= PULLED_OUT)), "near": float(near.mean()),
            "facing_near": float(facing[near].mean()), "gap_median": float(np.median(gaps))}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--room", default="diningroom")
    ap.add_argument("files", nargs="+", help="NAME=FILE: neutral-JSON scene files of the room type")
    args = ap.parse_args(argv)
    print("| scenes | rooms with a table and 2+ chairs | holds | chairs / room | at one table | chairs touching "
          "their table | pulled out (>= 0.15 m) | within 0.6 m | of those facing it | median gap (m) |")
    print("|---|" + "---:|" * 9)
    for arg in args.files:
        name, _, path = arg.rpartition("=")
        c = chair_placement(load_layouts(path, args.room))
        print(f"| {name or Path(path).stem} | {c['rooms']} | {c['holds']:.1%} | {c['chairs']:.2f} "
              f"| {c['at_table']:.2f} | {c['touching']:.1%} | {c['pulled_out']:.1%} | {c['near']:.1%} "
              f"| {c['facing_near']:.1%} "
              f"| {c['gap_median']:.2f} |")


if __name__ == "__main__":
    main()
