"""Which pairs of classes make Col_obj: for each scene file, Col_obj (the metric's colliding ground objects over
ground objects), the share of ground objects whose only collisions are the room's contact (a nightstand with a bed
in bedrooms, a seat with a table in living and dining rooms), Col_obj with that contact spared (overlaps up to the
stage-1 collision reward's ``contact`` volume: 0.04 m^3 in bedrooms, 0.11 in living and dining rooms), the least
Col_obj that keeps that contact (every other collision cleared, each object with a spared contact left where it is:
the most a stage 1 that keeps the contact can lower Col_obj to), the five
commonest colliding class pairs with their share of the colliding pairs and the median and largest overlap volume,
the same for the pairs beyond the contact with their penetration (m, along the shorter horizontal axis), and Col_obj
by the axis-aligned bounds of the turned footprints (the physics gradient's measure; the metric's is the oriented
boxes).
It shows how much of a collision fall comes from pulling objects out of the contact the data makes on purpose,
and how much collision is left beyond it.

    .venv/bin/python research/collision_pairs.py [--room bedroom] data=FLOORS.json prior=PRIOR.json stage1=STAGE1.json

Each argument is ``NAME=FILE`` (or a file, named by its stem): a neutral-JSON scene file of the room type.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from iarcs_env import geometry as geo  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64  # noqa: E402
from agents.train import load_train_config  # noqa: E402
from iarcs_env.relations import CLASS_GROUPS  # noqa: E402


#: The collision reward's ``contact`` of each room's stage-1 config: the pairs it spares, up to its volume.
STAGE1 = {"bedroom": "stage1_bedroom_geometry.yaml", "livingroom": "stage1_livingroom.yaml",
          "diningroom": "stage1_diningroom.yaml"}


def stage1_contact(room: str) -> dict:
    return load_train_config(REPO / "experiments" / STAGE1[room]).reward["collision"]["contact"]


def in_contact(contact: dict, a: str, b: str) -> bool:
    """Do classes ``a`` and ``b`` form one of ``contact``'s pairs (class or class-group names, either order)?"""
    def member(label, name):
        return label in CLASS_GROUPS.get(name, (name,))
    return any(member(a, x) and member(b, y) or member(b, x) and member(a, y) for x, y in contact["pairs"])


def collisions(layouts, room: str = "bedroom", chunk: int = 100) -> dict:
    pairs: dict[tuple[str, str], list[float]] = {}
    beyond: dict[tuple[str, str], list[float]] = {}  # penetration (m) of the pairs the contact does not spare
    volumes = []  # of the contact pairs
    contact = stage1_contact(room)
    colliding = ground = only_contact = colliding_beyond_contact = in_spared_contact = by_bounds = 0
    for s in range(0, len(layouts), chunk):
        part = layouts[s:s + chunk]
        batch = batch_float64(part)
        vol = geo.box_overlap_volumes(batch.translations, batch.half_sizes, batch.yaws, batch.ground_mask).numpy()
        hit = vol > geo.COLLISION_VOLUME
        ground_mask = batch.ground_mask.numpy()
        ground += int(ground_mask.sum())
        colliding += int(hit.any(2).sum())
        sep = geo.bounds_separations(batch.translations, batch.half_sizes, batch.yaws).numpy()
        bounds_hit = (sep.clip(0).prod(-1) > geo.COLLISION_VOLUME) & ground_mask[:, :, None] & ground_mask[:, None]
        bounds_hit[:, np.arange(sep.shape[1]), np.arange(sep.shape[1])] = False
        by_bounds += int(bounds_hit.any(2).sum())
        for k, lay in enumerate(part):
            for i, j in zip(*np.nonzero(np.triu(hit[k]))):
                pair = tuple(sorted((lay.labels[i], lay.labels[j])))
                pairs.setdefault(pair, []).append(float(vol[k, i, j]))
                if in_contact(contact, lay.labels[i], lay.labels[j]):
                    volumes.append(vol[k, i, j])
                    if vol[k, i, j] <= contact["volume"]:
                        continue
                beyond.setdefault(pair, []).append(float(min(sep[k, i, j, 0], sep[k, i, j, 2])))
            for i in range(len(lay)):
                partners = np.nonzero(hit[k, i])[0]
                only_contact += len(partners) > 0 and all(in_contact(contact, lay.labels[i], lay.labels[j])
                                                          for j in partners)
                spared = [in_contact(contact, lay.labels[i], lay.labels[j]) and vol[k, i, j] <= contact["volume"]
                          for j in partners]
                colliding_beyond_contact += not all(spared)
                in_spared_contact += any(spared)
    return {"Col_obj": colliding / ground, "only_contact": only_contact / ground, "pairs": pairs,
            "volumes": np.array(volumes), "Col_obj_beyond_contact": colliding_beyond_contact / ground,
            "Col_obj_contact_kept": in_spared_contact / ground, "beyond": beyond, "Col_obj_by_bounds": by_bounds / ground}


def share_of_pairs(pairs: dict, what: str, top: int = 5) -> str:
    """The ``top`` commonest class pairs of ``pairs`` (pair -> values), each with its share of all and the median and
    largest of its values (``what``); first the median over all."""
    values = [x for v in pairs.values() for x in v]
    if not values:
        return "none"
    rows = sorted(pairs.items(), key=lambda kv: -len(kv[1]))[:top]
    return f"{len(values)} pairs, {what} median {np.median(values):.3f}; " + "; ".join(
        f"{a}-{b} {len(v) / len(values):.0%} ({what} median {np.median(v):.3f}, max {max(v):.3f})"
        for (a, b), v in rows)


def main(args: list[str]) -> None:
    room = "bedroom"
    if args[:1] == ["--room"]:
        room, args = args[1], args[2:]
    if not args:
        sys.exit(__doc__)
    for arg in args:
        name, _, path = arg.rpartition("=")
        c = collisions(load_layouts(path, room), room)
        listed = share_of_pairs(c["pairs"], "overlap m^3")
        v = c["volumes"] if len(c["volumes"]) else np.zeros(1)
        what = "-".join(stage1_contact(room)["pairs"][0])
        contact = (f", of which {what} contact only {100 * c['only_contact']:.1f} points (Col_obj with {what} "
                   f"overlaps up to {stage1_contact(room)['volume']} m^3 spared: {100 * c['Col_obj_beyond_contact']:.1f}%; "
                   f"with every other collision cleared: {100 * c['Col_obj_contact_kept']:.1f}%) "
                   f"({what} overlap m^3 p50 {np.median(v):.3f} p90 {np.quantile(v, 0.9):.3f} max {v.max():.3f})")
        print(f"{name or Path(path).stem}: Col_obj {100 * c['Col_obj']:.1f}%{contact}; pairs: {listed}")
        print(f"  beyond the contact: {share_of_pairs(c['beyond'], 'penetration m')}; Col_obj by axis-aligned "
              f"bounds {100 * c['Col_obj_by_bounds']:.1f}%")


if __name__ == "__main__":
    main(sys.argv[1:])
