"""Objects per room, class by class, of scene files side by side: what a training run added or removed
(a bedroom without beds, rooms filled with pendant lamps) that the physical metrics do not show.

    .venv/bin/python benchmarks/class_counts.py prior=out/eval/X/prior.json stage2=out/eval/X/stage2.json

Each argument is ``NAME=FILE`` (or a file, named by its stem): a neutral-JSON scene file of one room type.
Rows: every class with at least ``--min`` objects per room in some file, then beds of any kind per room,
the share of rooms with a bed, and objects per room. ``--sizes MIN`` adds a second table, for each class
with at least MIN objects per room in the first file: the median footprint (m^2), bottom height (m) and
top height (m), and the share of its objects more than 0.05 m off the floor (R_off_floor by class; – for
ceiling and pendant lamps). It shows an adapter that changes sizes (a stage-2 run that lowers the beds), and
one that moves furniture off the floor: furniture stands on it (bottom 0), so a bottom far from 0 is an
object floating or sunk into the floor.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.geometry import FLOOR_CONTACT_TOL  # noqa: E402
from iarcs_env.rooms import CEILING_CLASSES  # noqa: E402


def class_counts(layouts) -> dict[str, float]:
    """Objects per room of each class, plus ``"bed (any)"``, ``"rooms with a bed %"`` and ``"objects"``."""
    n = max(len(layouts), 1)
    counts = Counter(label for lay in layouts for label in lay.labels)
    row = {label: k / n for label, k in counts.items()}
    row["bed (any)"] = sum(k for label, k in counts.items() if label.endswith("bed")) / n
    row["rooms with a bed %"] = 100 * sum(any(lbl.endswith("bed") for lbl in lay.labels) for lay in layouts) / n
    row["objects"] = sum(counts.values()) / n
    return row


def class_sizes(layouts) -> dict[str, tuple]:
    """Per class: medians over its objects of (footprint area m^2, bottom height m, top height m), then the %
    of its objects whose bottom is more than FLOOR_CONTACT_TOL from the floor (None for ceiling classes)."""
    values = {}
    for lay in layouts:
        for label, t, h in zip(lay.labels, lay.translations, lay.half_sizes):
            values.setdefault(label, []).append((4 * h[0] * h[2], t[1] - h[1], t[1] + h[1]))
    out = {}
    for c, v in values.items():
        off = None if c in CEILING_CLASSES else 100 * sum(abs(b) > FLOOR_CONTACT_TOL for _, b, _ in v) / len(v)
        out[c] = (*(statistics.median(column) for column in zip(*v)), off)
    return out


def _size_cell(size) -> str:
    area, bottom, top, off = size
    return f"{area:.2f} / {bottom:.2f} / {top:.2f} / " + ("–" if off is None else f"{off:.0f}%")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", help="NAME=FILE or FILE (neutral-JSON scenes)")
    p.add_argument("--min", type=float, default=0.02, help="smallest objects per room of a class to list")
    p.add_argument("--sizes", type=float, default=None, metavar="MIN",
                   help="also list median footprints, bottom and top heights, and the share off the floor, of the "
                        "classes with at least MIN objects per room in the first file")
    args = p.parse_args(argv)
    rows, sizes = {}, {}
    for item in args.files:
        name, _, path = item.rpartition("=")
        layouts = load_layouts(path, num_scenes=0)
        rows[name or Path(path).stem] = class_counts(layouts)
        sizes[name or Path(path).stem] = class_sizes(layouts)
    summary = ["bed (any)", "rooms with a bed %", "objects"]
    first = next(iter(rows.values()))
    classes = sorted({c for row in rows.values() for c, v in row.items() if c not in summary and v >= args.min},
                     key=lambda c: -first.get(c, 0.0))
    print("| per room | " + " | ".join(rows) + " |\n|---|" + "---|" * len(rows))
    for c in classes + summary:
        fmt = "{:.1f}" if c.endswith("%") else "{:.2f}"
        print(f"| {c} | " + " | ".join(fmt.format(row.get(c, 0.0)) for row in rows.values()) + " |")
    if args.sizes is not None:
        print("\n| footprint m^2 / bottom m / top m (medians) / off the floor | " + " | ".join(rows) + " |\n|---|"
              + "---|" * len(rows))
        for c in [c for c in classes if first.get(c, 0.0) >= args.sizes]:
            print(f"| {c} | " + " | ".join(_size_cell(size[c]) if c in size else "–" for size in sizes.values()) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
