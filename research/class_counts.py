"""Objects per room, class by class, of scene files side by side: what a training run added or removed
(a bedroom without beds, rooms filled with pendant lamps) that the physical metrics do not show.

    .venv/bin/python research/class_counts.py prior=out/eval/X/prior.json stage2=out/eval/X/stage2.json

Each argument is ``NAME=FILE`` (or a file, named by its stem): a neutral-JSON scene file of one room type;
``NAME=FILE,FILE,...`` pools several (e.g. one per sampling seed) into one column.
Rows: every class with at least ``--min`` objects per room in some file, then beds of any kind per room,
the share of rooms with a bed, and objects per room. ``--sizes MIN`` adds a second table, for each class
with at least MIN objects per room in the first file: the median footprint (m^2), bottom height (m) and
top height (m), and the share of its objects more than 0.05 m off the floor (R_off_floor by class; – for
ceiling and pendant lamps). It shows an adapter that changes sizes (a stage-2 run that lowers the beds), and
one that moves furniture off the floor: furniture stands on it (bottom 0), so a bottom far from 0 is an
object floating or sunk into the floor; its last row is each file's ``footprint_change`` against the first
file (:func:`iarcs_env.metrics.footprint_change`). ``--out-of-bound`` adds, for each file, which classes the
objects out of the room (R_out's definition) are: per class its share of them and the share of its own objects that are
out, and the median area outside (m^2) of all of them; then R_out by the number of corners of the floor
(4: rectangles, 6: L-shaped rooms, ...).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env import geometry as geo  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64, footprint_change  # noqa: E402
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


def out_of_bound_by_class(layouts) -> tuple[dict[str, tuple[int, int]], list[float], dict[int, tuple[int, int, int]]]:
    """Per class (objects out of bound, objects), with R_out's definition (footprint shrunk by 0.05 m, more
    than 1e-5 m^2 outside the floor); the area outside (m^2) of every object out of bound; and per number of
    floor corners (4: a rectangle, 6: an L) (rooms, objects out of bound, objects)."""
    counts, areas, shapes = {}, [], {}
    for start in range(0, len(layouts), 256):
        chunk = layouts[start:start + 256]
        b = batch_float64(chunk)
        area = geo.box_out_of_floor_area(b.translations, b.half_sizes, b.yaws, b.floors, b.mask,
                                         geo.OUT_OF_BOUND_SHRINK)
        for i, lay in enumerate(chunk):
            out = area[i, :len(lay)] > geo.OUT_OF_BOUND_AREA  # the batch holds each room's objects in its slots
            for label, is_out, a in zip(lay.labels, out.tolist(), area[i].tolist()):
                n_out, n = counts.get(label, (0, 0))
                counts[label] = (n_out + is_out, n + 1)
                if is_out:
                    areas.append(a)
            rooms, n_out, n = shapes.get(len(lay.floor.vertices), (0, 0, 0))
            shapes[len(lay.floor.vertices)] = (rooms + 1, n_out + int(out.sum()), n + len(lay))
    return counts, areas, dict(sorted(shapes.items()))


def _print_out_of_bound(name: str, layouts) -> None:
    counts, areas, shapes = out_of_bound_by_class(layouts)
    total = max(len(areas), 1)
    median = statistics.median(areas) if areas else 0.0
    print(f"\n{name}: {len(areas)} objects out of bound, median area outside {median:.3f} m^2\n"
          "| class | share of the out-of-bound objects | its objects out of bound |\n|---|---|---|")
    for label, (n_out, n) in sorted(counts.items(), key=lambda kv: -kv[1][0]):
        if n_out:
            print(f"| {label} | {n_out / total:.2f} | {n_out} / {n} |")
    print("\n| floor corners | rooms | R_out |\n|---|---|---|")
    for corners, (rooms, n_out, n) in shapes.items():
        print(f"| {corners} | {rooms} | {n_out / max(n, 1):.3f} |")


def _size_cell(size) -> str:
    area, bottom, top, off = size
    return f"{area:.2f} / {bottom:.2f} / {top:.2f} / " + ("–" if off is None else f"{off:.0f}%")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", help="NAME=FILE, NAME=FILE,FILE,... (pooled) or FILE (neutral-JSON scenes)")
    p.add_argument("--min", type=float, default=0.02, help="smallest objects per room of a class to list")
    p.add_argument("--sizes", type=float, default=None, metavar="MIN",
                   help="also list median footprints, bottom and top heights, and the share off the floor, of the "
                        "classes with at least MIN objects per room in the first file")
    p.add_argument("--out-of-bound", action="store_true",
                   help="also list, per file, the classes of the objects out of the room and the median area outside")
    args = p.parse_args(argv)
    rows, sizes, files = {}, {}, {}
    for item in args.files:
        name, _, path = item.rpartition("=")
        name = name or Path(path).stem
        files[name] = layouts = [lay for part in path.split(",") for lay in load_layouts(part, num_scenes=0)]
        rows[name] = class_counts(layouts)
        sizes[name] = class_sizes(layouts)
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
        reference = next(iter(files.values()))
        changes = [footprint_change(reference, layouts) for layouts in files.values()]
        print("| footprints against the first file's, all classes (geometric mean) | "
              + " | ".join(f"{100 * ch['all']:+.1f}%" for ch in changes) + " |")
    if args.out_of_bound:
        for name, layouts in files.items():
            _print_out_of_bound(name, layouts)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
