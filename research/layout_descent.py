"""How far the physics penalty can take a prior's own rooms when every object is free to move: descent on the
layouts themselves, no network. Asks whether the living-room stage-1 adapters failed to learn, or whether the rooms
have no way down that keeps their relations and walkways (issue 39).

    .venv/bin/python research/layout_descent.py --room livingroom PRIOR.json --out DESCENDED.json \\
        [--steps 300] [--reach-weight 5] [--out-of-bound-weight 5] [--out-of-bound-shrink 0] [--refresh 20] \\
        [--contact-gap-weight 3 --contact-gap 0.12 [--contact-gap-walkway]] [--passage-weight 1]
    iarcs evaluate --scenes DESCENDED.json --reference floors.json --features none --out report.json

Each room's objects move on the floor (x and z; heights, sizes, yaws and classes kept) by
:func:`agents.descent_imitation.descend_layouts` (Adam on :func:`agents.physics_gradient.layout_penalty`), at the
weights of the depth configs (`experiments/ablations/stage1_ROOM_depth.yaml`): each overlapping pair its penetration
depth, the out-of-bound area weighed 5 (``--out-of-bound-weight``), the data's contact spared (seat-table in living
and dining rooms, nightstand-bed in bedrooms); ``--reach-weight`` adds the walkway term, ``--out-of-bound-shrink 0``
charges the whole footprint's area outside (R_out spares 0.05 m a side; without the margin the walkway term rests
objects just through a wall). The contact pairs are not charged (depth) unless ``--contact-gap-weight`` draws each
to a gap, as ``ddpo.contact_gap_weight`` does; ``--passage-weight`` closes or opens each gap too narrow to walk
through, as ``ddpo.passage_weight`` does.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CONTACT = {"livingroom": {"pairs": [["seat", "table"]], "volume": 0.11},
           "diningroom": {"pairs": [["seat", "table"]], "volume": 0.11},
           "bedroom": {"pairs": [["nightstand", "bed"]], "volume": 0.04}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="a layout file (the prior's samples)")
    parser.add_argument("--room", required=True, choices=sorted(CONTACT))
    parser.add_argument("--out", required=True, help="where to write the moved rooms (neutral JSON)")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--reach-weight", type=float, default=0.0)
    parser.add_argument("--out-of-bound-weight", type=float, default=5.0)
    parser.add_argument("--out-of-bound-shrink", type=float, default=0.05)
    parser.add_argument("--contact-gap-weight", type=float, default=0.0,
                        help="> 0: a contact pair within 0.6 m drawn to --contact-gap (ddpo.contact_gap_weight)")
    parser.add_argument("--contact-gap", type=float, default=0.05)
    parser.add_argument("--contact-gap-walkway", action="store_true",
                        help="draw a pair out only where a walkway stays behind it (ddpo.contact_gap_walkway)")
    parser.add_argument("--passage-weight", type=float, default=0.0,
                        help="> 0: each gap too narrow to walk through closed or opened (ddpo.passage_weight)")
    parser.add_argument("--refresh", type=int, default=20, help="steps between the walkway term's grid searches")
    args = parser.parse_args()
    import torch

    from agents.descent_imitation import descend_layouts
    from agents.physics_gradient import layout_penalty
    from iarcs_env.datasets import load_layouts, save_layouts
    from iarcs_env.scene import SceneBatch

    torch.set_num_threads(1)
    layouts = load_layouts(args.scenes, args.room)
    weights = dict(out_of_bound_weight=args.out_of_bound_weight, out_of_bound_shrink=args.out_of_bound_shrink,
                   contact=CONTACT[args.room], overlap_measure="depth", contact_gap_weight=args.contact_gap_weight,
                   contact_gap=args.contact_gap, contact_gap_walkway=args.contact_gap_walkway,
                   passage_weight=args.passage_weight)
    out, before, after = [], [], []
    for start in range(0, len(layouts), 50):
        batch = SceneBatch.from_layouts(layouts[start:start + 50])
        parts = (batch.half_sizes, batch.yaws, batch.labels, batch.spec, batch.floors)
        moved = descend_layouts(batch.translations, *parts, steps=args.steps, reach_weight=args.reach_weight,
                                refresh=args.refresh, **weights)
        before.append(layout_penalty(batch.translations, *parts, **weights))
        after.append(layout_penalty(moved, *parts, **weights))
        batch.translations = moved
        out += batch.to_layouts()
        print(f"{len(out)} of {len(layouts)} rooms", file=sys.stderr)
    save_layouts(out, args.out)
    print(f"penalty per room without the walkway term: {torch.cat(before).mean():.3f} -> "
          f"{torch.cat(after).mean():.3f}; wrote {args.out}")


if __name__ == "__main__":
    main()
