"""The rooms of a layout file that pass a paper task's checker, written as a layout file of their own: the
3D-FRONT* rows of Table 3 (the real rooms satisfying each task, evaluated like the samples).

    .venv/bin/python research/passing_rooms.py ../shared/data/3dfront/bedroom_val.json two_nightstands --out F.json
    iarcs evaluate --scenes F.json --task two_nightstands --features none --out F_report.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402


def passing(layouts, task: str) -> list:
    """The layouts that pass ``task``'s checker, in their order."""
    return [lay for lay, ok in zip(layouts, task_results(task, layouts)) if ok]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="a layout file")
    parser.add_argument("task", help="reach_1m, tv_from_bed, study_zone, two_nightstands or wheelchair")
    parser.add_argument("--out", required=True, help="layout file to write")
    args = parser.parse_args()
    layouts = load_layouts(args.scenes, "bedroom")
    kept = passing(layouts, args.task)
    save_layouts(kept, args.out, source=f"{args.scenes}, passing {args.task}")
    print(f"{len(kept)} of {len(layouts)} rooms pass {args.task}: {args.out}")


if __name__ == "__main__":
    main()
