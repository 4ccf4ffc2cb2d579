"""What the physics gradient's terms do to a seat at its desk: why the bedroom stage-1 adapter loses study_zone.

    .venv/bin/python research/seat_desk_pulls.py PRIOR_SAMPLES.json [MORE.json ...]
    .venv/bin/python research/seat_desk_pulls.py --lost PRIOR_S0.json RUN_S0.json [PRIOR_S1.json RUN_S1.json ...]

For every room where study_zone holds (a seat in front of a desk, ``iarcs_env.tasks.check_study_zone``), the room's
first desk and first seat are taken and each term of :func:`agents.physics_gradient.physics_penalty` (at the shipped
stage-1 config's weights: depth 1, out-of-bound 5, walkway 5) is differentiated at the room's layout. The descent
direction of the seat relative to its desk is read in the desk's frame: lateral (along its width) and forward
(positive: away from the desk's front, where study_zone wants the seat). The walkway term is split into the seat's
own shortfall (its path too narrow) and the other objects' (the seat standing in their path). Printed per term: the
rooms where it moves the seat, how many of them backward (towards or behind the desk's centre) or mostly sideways.

``--lost`` compares files sampled on the same floors with the same seed, in pairs (the prior's, then a run's): the
rooms where study_zone holds in the first and not in the second (and the other way round), and where the second
put the seat nearest to a desk: behind the desk's centre, sideways (beyond its width + 0.1 m), more than 0.9 m out
in front, or no desk or no seat left in the room.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SEATS = ("chair", "stool", "dressing_chair")
CONTACT = {"pairs": [["nightstand", "bed"]], "volume": 0.04}


def seat_pulls(layout, stats) -> dict[str, tuple[float, float]]:
    """{term: (lateral, forward)}: the descent direction of the seat relative to the desk, in the desk's frame."""
    import numpy as np
    import torch

    from agents.physics_gradient import physics_penalty
    from iarcs_env import geometry as geo
    from iarcs_env.clearance import reach_clearance
    from iarcs_env.scene import SceneBatch, decode_geometry, floor_half_extents

    batch = SceneBatch.from_layouts([layout])
    labels = list(layout.labels)
    desk = labels.index("desk")
    seat = next(i for i, label in enumerate(labels) if label in SEATS)
    yaw = float(np.ravel(layout.yaws)[desk])

    def walkway(x, own: bool):
        trans, half, yaws = decode_geometry(x, stats, floor_half_extents(batch.floors).to(x))
        classes = x[..., 8:].argmax(-1)
        ground = torch.tensor(stats.spec.ground_mask())[classes] & (classes != stats.spec.empty_index)
        short = 5.0 * (geo.AGENT_RADIUS - reach_clearance(batch.floors, trans, half, yaws, ground, geo.AGENT_RADIUS))
        short = short.clamp_min(0)[0]
        return short[seat] if own else short.sum() - short[seat]

    terms = {
        "overlap depth": lambda x: physics_penalty(x, stats, batch.floors, contact=CONTACT, overlap_measure="depth",
                                                   out_of_bound_weight=0.0),
        "overlap depth, seat-desk uncharged": lambda x: physics_penalty(
            x, stats, batch.floors, contact=CONTACT, overlap_measure="depth", out_of_bound_weight=0.0,
            uncharged_pairs=[["seat", "desk"]]),
        "out of bound x5": lambda x: physics_penalty(x, stats, batch.floors, overlap_weight=0.0,
                                                     out_of_bound_weight=5.0),
        "walkway x5, the seat's own path": lambda x: walkway(x, own=True),
        "walkway x5, the others' paths": lambda x: walkway(x, own=False),
    }
    pulls = {}
    for name, term in terms.items():
        x = batch.encode(stats).clone().requires_grad_(True)
        value = term(x).sum()
        grad = torch.autograd.grad(value, x, allow_unused=True)[0] if value.requires_grad else None
        if grad is None:
            pulls[name] = (0.0, 0.0)
            continue
        step = -(grad[0, seat, [0, 2]] - grad[0, desk, [0, 2]]).numpy()
        pulls[name] = (float(np.cos(yaw) * step[0] - np.sin(yaw) * step[1]),
                       float(np.sin(yaw) * step[0] + np.cos(yaw) * step[1]))
    return pulls


def where_the_seat_went(layout) -> str:
    """Why study_zone fails in ``layout``: the nearest seat to a desk, read in that desk's frame."""
    import numpy as np

    labels = list(layout.labels)
    desks = [i for i, label in enumerate(labels) if label == "desk"]
    seats = [i for i, label in enumerate(labels) if label in SEATS]
    if not desks or not seats:
        return "no desk or no seat"
    t, h, yaws = np.asarray(layout.translations), np.asarray(layout.half_sizes), np.ravel(layout.yaws)
    distance, desk, seat = min((float(np.hypot(*(t[c, 0:3:2] - t[d, 0:3:2]))), d, c) for d in desks for c in seats)
    dx, dz = t[seat, 0:3:2] - t[desk, 0:3:2]
    lateral = np.cos(yaws[desk]) * dx - np.sin(yaws[desk]) * dz
    forward = np.sin(yaws[desk]) * dx + np.cos(yaws[desk]) * dz
    return ("behind the desk's centre" if forward <= 0 else "sideways" if abs(lateral) > h[desk, 0] + 0.1
            else "too far in front")


def lost_rooms(pairs: list[tuple[str, str]]) -> dict[str, int]:
    """Over (before, after) file pairs: rooms that lost and gained study_zone, and where the lost ones' seat went."""
    from collections import Counter

    import numpy as np

    from iarcs_env.datasets import load_layouts
    from iarcs_env.scene import SceneBatch
    from iarcs_env.tasks import check_study_zone

    counts = Counter()
    for before, after in pairs:
        a, b = load_layouts(before, "bedroom"), load_layouts(after, "bedroom")
        held, holds = (check_study_zone(SceneBatch.from_layouts(x)) for x in (a, b))
        counts["lost"] += int((held & ~holds).sum())
        counts["gained"] += int((~held & holds).sum())
        for i in np.nonzero(held & ~holds)[0]:
            counts[where_the_seat_went(b[i])] += 1
    return dict(counts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", help="neutral-JSON bedroom scene files (e.g. the prior's samples)")
    parser.add_argument("--lost", action="store_true", help="the files are (prior, run) pairs: where the seats went")
    args = parser.parse_args()
    if args.lost:
        if len(args.files) % 2:
            parser.error("--lost takes files in pairs: the prior's samples, then the run's, on the same floors")
        print(lost_rooms(list(zip(args.files[::2], args.files[1::2]))))
        return
    import numpy as np

    from iarcs_env.datasets import load_layouts
    from iarcs_env.env import default_stats
    from iarcs_env.scene import SceneBatch
    from iarcs_env.tasks import check_study_zone

    stats = default_stats("bedroom")
    rows: dict[str, list] = {}
    for path in args.files:
        layouts = [layout.centred() for layout in load_layouts(path, "bedroom")]
        for i in np.nonzero(check_study_zone(SceneBatch.from_layouts(layouts)))[0]:
            for name, pull in seat_pulls(layouts[i], stats).items():
                rows.setdefault(name, []).append(pull)
    print("| term | rooms | seat moved | of those backward | mostly sideways |")
    print("|---|---:|---:|---:|---:|")
    for name, pulls in rows.items():
        v = np.array(pulls)
        moved = np.abs(v).sum(1) > 1e-6
        print(f"| {name} | {len(v)} | {moved.sum()} | {((v[:, 1] < 0) & moved).sum()} | "
              f"{((np.abs(v[:, 0]) > np.abs(v[:, 1])) & moved).sum()} |")


if __name__ == "__main__":
    main()
