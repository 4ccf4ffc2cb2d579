"""The data's own rooms of the floors on which a prior's samples put an object out of bound (R_out's definition),
written as a layout file: the hard floors, to weigh up in a fine-tune (tried for Table 4's R_out,
``docs/results/augmentation.md``, "Tried on R_out, did not help"). Sample files are matched to the data by room id
(``iarcs sample --floors DATA.json`` keeps each floor's id before its ``:``).

    .venv/bin/python research/out_of_bound_floors.py DATA.json S0.json S1.json --out HARD.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64, evaluate_batch  # noqa: E402


def out_of_bound_floors(samples, chunk: int = 250) -> dict[str, int]:
    """Floor id -> objects out of bound on it, over the given sampled rooms (floors with none left out)."""
    found: dict[str, int] = {}
    for k in range(0, len(samples), chunk):
        part = samples[k:k + chunk]
        for lay, scene in zip(part, evaluate_batch(batch_float64(part)).scenes):
            if scene.out_of_bound:
                floor = lay.id.split(":")[0]
                found[floor] = found.get(floor, 0) + len(scene.out_of_bound)
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", help="the layout file whose floors were sampled")
    parser.add_argument("samples", nargs="+", help="the prior's samples on those floors, one file per sampling")
    parser.add_argument("--room", default="bedroom")
    parser.add_argument("--out", required=True, help="layout file to write")
    args = parser.parse_args(argv)
    found = out_of_bound_floors([lay for f in args.samples for lay in load_layouts(f, args.room, num_scenes=0)])
    hard = [lay for lay in load_layouts(args.data, args.room, num_scenes=0) if lay.id in found]
    save_layouts(hard, args.out, source=f"{args.data}: the floors out of bound in {', '.join(args.samples)}")
    print(f"{sum(found.values())} objects out of bound on {len(found)} floors; {len(hard)} data rooms: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
