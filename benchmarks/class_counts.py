"""Objects per room, class by class, of scene files side by side: what a training run added or removed
(a bedroom without beds, rooms filled with pendant lamps) that the physical metrics do not show.

    .venv/bin/python benchmarks/class_counts.py prior=out/eval/X/prior.json stage2=out/eval/X/stage2.json

Each argument is ``NAME=FILE`` (or a file, named by its stem): a neutral-JSON scene file of one room type.
Rows: every class with at least ``--min`` objects per room in some file, then beds of any kind per room,
the share of rooms with a bed, and objects per room.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402


def class_counts(layouts) -> dict[str, float]:
    """Objects per room of each class, plus ``"bed (any)"``, ``"rooms with a bed %"`` and ``"objects"``."""
    n = max(len(layouts), 1)
    counts = Counter(label for lay in layouts for label in lay.labels)
    row = {label: k / n for label, k in counts.items()}
    row["bed (any)"] = sum(k for label, k in counts.items() if label.endswith("bed")) / n
    row["rooms with a bed %"] = 100 * sum(any(lbl.endswith("bed") for lbl in lay.labels) for lay in layouts) / n
    row["objects"] = sum(counts.values()) / n
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", help="NAME=FILE or FILE (neutral-JSON scenes)")
    p.add_argument("--min", type=float, default=0.02, help="smallest objects per room of a class to list")
    args = p.parse_args(argv)
    rows = {}
    for item in args.files:
        name, _, path = item.rpartition("=")
        rows[name or Path(path).stem] = class_counts(load_layouts(path, num_scenes=0))
    summary = ["bed (any)", "rooms with a bed %", "objects"]
    first = next(iter(rows.values()))
    classes = sorted({c for row in rows.values() for c, v in row.items() if c not in summary and v >= args.min},
                     key=lambda c: -first.get(c, 0.0))
    print("| per room | " + " | ".join(rows) + " |\n|---|" + "---|" * len(rows))
    for c in classes + summary:
        fmt = "{:.1f}" if c.endswith("%") else "{:.2f}"
        print(f"| {c} | " + " | ".join(fmt.format(row.get(c, 0.0)) for row in rows.values()) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
