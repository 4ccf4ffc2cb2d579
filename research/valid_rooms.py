"""The rooms of a layout file that pass the universal checkers and keep the room type's relations, written as a
layout file of their own: no object out of bound, none off the floor, and (with ``--relations``) every relation
whose objects the room holds also holds (``iarcs_env/relation_fidelity.py``: a bed with two nightstands has them
at its head, a TV stand and a bed face each other, ...). Used to try augmentation with only those of the
generated rooms (Table 4, ``docs/results/augmentation.md``); with ``--out-of-bound CLASS ...`` only an object of
those classes out of bound drops a room (the prior's training rooms with a bed out of bound left out; no class named:
any object out of bound).

    .venv/bin/python research/valid_rooms.py AUG/scenes.json --room bedroom --relations --limit 4000 --out VALID.json
    .venv/bin/python research/valid_rooms.py procedural --num-scenes 20000 --room bedroom \
        --out-of-bound double_bed kids_bed single_bed --out DATA.json
    .venv/bin/python research/valid_rooms.py AUG/scenes.json --room bedroom --out-of-bound --out ROOMS.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64, evaluate_batch  # noqa: E402
from iarcs_env.relation_fidelity import relation_flags  # noqa: E402


def valid(layouts, room: str, relations: bool, out_classes=None, chunk: int = 250) -> np.ndarray:
    """Per room: no object out of bound or off the floor (with ``out_classes``: no object of those classes out of
    bound) and, with ``relations``, no relation whose objects co-occur without holding."""
    keep = []
    for k in range(0, len(layouts), chunk):
        batch = batch_float64(layouts[k:k + chunk])
        res = evaluate_batch(batch)
        if out_classes is not None:  # [] : any class
            named = np.isin(batch.labels.numpy(), [batch.spec.classes.index(c) for c in out_classes]) \
                if out_classes else np.ones(batch.labels.shape, dtype=bool)
            keep += list(~(res.out_of_bound & named).any(1))
        else:
            keep += [not (s.out_of_bound or s.off_floor) for s in res.scenes]
    keep = np.array(keep)
    if relations:
        for co, holds in relation_flags(layouts, room).values():
            keep &= ~co | holds
    return keep


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="a layout file, or procedural")
    parser.add_argument("--num-scenes", type=int, default=1000, help="procedural: this many rooms (seed 0, the "
                        "priors' training floors)")
    parser.add_argument("--room", default="bedroom")
    parser.add_argument("--out-of-bound", nargs="*", metavar="CLASS",
                        help="drop only rooms with an object out of bound (of these classes, if named)")
    parser.add_argument("--relations", action="store_true",
                        help="also drop rooms where a relation's objects co-occur and it does not hold")
    parser.add_argument("--limit", type=int, default=None, help="keep at most this many rooms, in order")
    parser.add_argument("--out", required=True, help="layout file to write")
    args = parser.parse_args()
    layouts = load_layouts(args.scenes, args.room, num_scenes=args.num_scenes, seed=0)
    kept = [lay for lay, ok in zip(layouts, valid(layouts, args.room, args.relations, args.out_of_bound))
            if ok][:args.limit]
    kind = "valid rooms" if args.out_of_bound is None else f"no {', '.join(args.out_of_bound) or 'object'} out of bound"
    save_layouts(kept, args.out, source=f"{args.scenes}, {kind}" + (", relations kept" if args.relations else ""))
    print(f"{len(kept)} of {len(layouts)} rooms kept: {args.out}")


if __name__ == "__main__":
    main()
