"""Which pairs of classes make Col_obj: for each scene file, Col_obj (the metric's colliding ground objects over
ground objects), the share of ground objects whose only collisions are with a bed while being a nightstand (or
the reverse), Col_obj with the data's nightstand-bed contact spared (overlaps up to 0.04 m^3, as stage 1's
collision reward spares them), the five commonest colliding class pairs with their share of the colliding pairs
and the median and largest overlap volume. It shows how much of a collision fall comes from pulling nightstands off
their bed, whose box the data's nightstands overlap on purpose, and which pairs the data itself puts in contact
(the collision reward's ``contact``).

    .venv/bin/python research/collision_pairs.py [--room bedroom] data=FLOORS.json prior=PRIOR.json stage1=STAGE1.json

Each argument is ``NAME=FILE`` (or a file, named by its stem): a neutral-JSON scene file of the room type.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env import geometry as geo  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64  # noqa: E402
from iarcs_env.relations import BEDS  # noqa: E402


def nightstand_bed(a: str, b: str) -> bool:
    return {a, b} & {"nightstand"} and {a, b} & set(BEDS) and a != b


CONTACT_VOLUME = 0.04
"""m^3: the largest nightstand-bed overlap of the procedural data, spared by stage 1's collision reward
(experiments/stage1_bedroom_geometry.yaml)."""


def collisions(layouts, chunk: int = 100) -> dict:
    pairs: dict[tuple[str, str], list[float]] = {}
    volumes = []  # of the nightstand-bed pairs (any bed)
    colliding = ground = only_nightstand_bed = colliding_beyond_contact = 0
    for s in range(0, len(layouts), chunk):
        part = layouts[s:s + chunk]
        batch = batch_float64(part)
        vol = geo.box_overlap_volumes(batch.translations, batch.half_sizes, batch.yaws, batch.ground_mask).numpy()
        hit = vol > geo.COLLISION_VOLUME
        ground += int(batch.ground_mask.sum())
        colliding += int(hit.any(2).sum())
        for k, lay in enumerate(part):
            for i, j in zip(*np.nonzero(np.triu(hit[k]))):
                pairs.setdefault(tuple(sorted((lay.labels[i], lay.labels[j]))), []).append(float(vol[k, i, j]))
                if nightstand_bed(lay.labels[i], lay.labels[j]):
                    volumes.append(vol[k, i, j])
            for i in range(len(lay)):
                partners = np.nonzero(hit[k, i])[0]
                only_nightstand_bed += len(partners) > 0 and all(nightstand_bed(lay.labels[i], lay.labels[j])
                                                                 for j in partners)
                colliding_beyond_contact += any(not nightstand_bed(lay.labels[i], lay.labels[j])
                                                or vol[k, i, j] > CONTACT_VOLUME for j in partners)
    return {"Col_obj": colliding / ground, "only_nightstand_bed": only_nightstand_bed / ground, "pairs": pairs,
            "volumes": np.array(volumes), "Col_obj_beyond_contact": colliding_beyond_contact / ground}


def main(args: list[str]) -> None:
    room = "bedroom"
    if args[:1] == ["--room"]:
        room, args = args[1], args[2:]
    if not args:
        sys.exit(__doc__)
    for arg in args:
        name, _, path = arg.rpartition("=")
        c = collisions(load_layouts(path, room))
        total = sum(len(v) for v in c["pairs"].values())
        top = sorted(c["pairs"].items(), key=lambda kv: -len(kv[1]))[:5]
        listed = "; ".join(f"{a}-{b} {len(v) / total:.0%} (overlap m^3 median {np.median(v):.3f}, max {max(v):.3f})"
                           for (a, b), v in top)
        v = c["volumes"]
        contact = (f", of which nightstand-bed contact only {100 * c['only_nightstand_bed']:.1f} points "
                   f"(Col_obj with nightstand-bed overlaps up to {CONTACT_VOLUME} m^3 spared: "
                   f"{100 * c['Col_obj_beyond_contact']:.1f}%) "
                   f"(nightstand-bed overlap m^3 p50 {np.median(v):.3f} p90 {np.quantile(v, 0.9):.3f} "
                   f"max {v.max():.3f})"
                   if room == "bedroom" else "")
        print(f"{name or Path(path).stem}: Col_obj {100 * c['Col_obj']:.1f}%{contact}; pairs: {listed}")


if __name__ == "__main__":
    main(sys.argv[1:])
