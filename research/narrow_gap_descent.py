"""Can a rule local to each pair of objects keep the dining walkways? The layout descent of
``research/layout_descent.py`` (each overlap its depth, the walls weighed 20, whole footprints kept inside; the
seat-table contact spared unless ``--charge-contact``; ``--contact-gap-weight`` > 0 draws each chair to 0.12 m from its
table, ``--gated`` only where no passage narrows) plus ``--weight`` times :func:`agents.physics_gradient.narrow_passages`
(``ddpo.passage_weight``): each gap between two objects or an object and a wall too narrow for R_reach's agent is
closed or opened to its width. No walkway grid: only each pair's own gap.

    .venv/bin/python research/narrow_gap_descent.py PRIOR.json OUT.json --weight 1 [--contact-gap-weight 3 [--gated]] \\
        [--charge-contact]
    iarcs evaluate --scenes OUT.json --reference floors.json --features none
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.descent_imitation import DESCENT_LR  # noqa: E402
from agents.physics_gradient import layout_penalty  # noqa: E402
from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402

SEAT_AT_TABLE = {"pairs": [["seat", "table"]], "volume": 0.11}


def descend(batch: SceneBatch, weight: float, contact: dict | None, contact_gap_weight: float, gated: bool,
            steps: int = 300) -> torch.Tensor:
    """Translations of ``batch`` moved on the floor by ``steps`` steps of Adam down the penalty (module doc)."""
    trans0, half, yaws = batch.translations.double(), batch.half_sizes.double(), batch.yaws.double()
    valid = batch.labels != batch.spec.empty_index
    delta = torch.zeros(trans0.shape[:2] + (2,), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=DESCENT_LR)

    def moved(d: torch.Tensor) -> torch.Tensor:
        move = d * valid[..., None]
        return trans0 + torch.stack([move[..., 0], torch.zeros_like(move[..., 0]), move[..., 1]], -1)

    for _ in range(steps):
        trans = moved(delta)
        loss = layout_penalty(trans, half, yaws, batch.labels, batch.spec, batch.floors, out_of_bound_weight=20.0,
                              out_of_bound_shrink=0.0, contact=contact, overlap_measure="depth",
                              contact_gap_weight=contact_gap_weight, contact_gap=0.12,
                              contact_gap_walkway=gated, passage_weight=weight)
        optimizer.zero_grad()
        loss.sum().backward()
        optimizer.step()
    return moved(delta.detach()).to(batch.translations.dtype)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="a dining-room layout file (the prior's samples)")
    parser.add_argument("out", help="where to write the moved rooms")
    parser.add_argument("--weight", type=float, required=True, help="the tent's weight")
    parser.add_argument("--contact-gap-weight", type=float, default=0.0)
    parser.add_argument("--charge-contact", action="store_true", help="charge the seat-table overlap as any other")
    parser.add_argument("--gated", action="store_true",
                        help="draw a chair out only where no passage narrows (ddpo.contact_gap_walkway)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    layouts = load_layouts(args.scenes, "diningroom")
    out = []
    for start in range(0, len(layouts), 50):
        batch = SceneBatch.from_layouts(layouts[start:start + 50])
        batch.translations = descend(batch, args.weight, None if args.charge_contact else SEAT_AT_TABLE,
                                     args.contact_gap_weight, args.gated)
        out += batch.to_layouts()
        print(f"{len(out)} of {len(layouts)} rooms", file=sys.stderr)
    save_layouts(out, args.out)


if __name__ == "__main__":
    main()
