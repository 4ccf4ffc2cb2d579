"""Can a rule local to each pair of objects keep the dining walkways? The layout descent of
``research/layout_descent.py`` (each overlap its depth, the walls weighed 20, whole footprints kept inside; the
seat-table contact spared unless ``--charge-contact``; ``--contact-gap-weight`` > 0 draws each chair to 0.12 m from its
table) plus a tent on every gap g between two ground objects' bounds (not seat-table, not seat-seat) and between an
object and a wall: ``--weight`` * min(g - 0.05, 0.6 - g) while 0.05 < g < 0.6, so each gap either closes or opens to
R_reach's agent (0.6 m wide); with ``--relative``, a gap the room had narrow (0.05 < g0 < 0.6) only kept from
narrowing: its tent's apex is g0. No walkway grid: only each pair's own gap.

    .venv/bin/python research/narrow_gap_descent.py PRIOR.json OUT.json --weight 1 [--contact-gap-weight 3] \\
        [--charge-contact] [--relative]
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
from iarcs_env import geometry as geo  # noqa: E402
from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402
from iarcs_env.relations import _point_segment_distance, class_mask, floor_edges  # noqa: E402
from iarcs_env.scene import SceneBatch, footprint_reach  # noqa: E402

CLOSED = 0.05
"""m: a gap this narrow counts as touching (uncharged)."""
SEAT_AT_TABLE = {"pairs": [["seat", "table"]], "volume": 0.11}
EDGE_POINTS = torch.tensor([[1, 1], [1, -1], [-1, 1], [-1, -1], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=torch.float64)


def tent(gap: torch.Tensor, apex: torch.Tensor | float = 2 * geo.AGENT_RADIUS) -> torch.Tensor:
    """min(g - CLOSED, apex - g) for CLOSED < g < apex (by default 2r, r: R_reach's agent radius), else 0."""
    inside = (gap > CLOSED) & (gap < apex)
    return torch.where(inside, torch.minimum(gap - CLOSED, apex - gap), torch.zeros_like(gap))


def apexes(gaps: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """``--relative``: each tent's apex from the room's gaps before the descent (``narrow_gaps(..., gaps_only=True)``):
    a gap that was already narrow (CLOSED < g0 < 2r) keeps g0, so only narrowing it further is charged; every other
    gap, 2r."""
    width = 2 * geo.AGENT_RADIUS
    return tuple(torch.where((g > CLOSED) & (g < width), g, torch.full_like(g, width)) for g in gaps)


def narrow_gaps(trans, half, yaws, labels, spec, floors, apex=(2 * geo.AGENT_RADIUS,) * 2, gaps_only=False):
    """(B,) the tent summed over the gaps between ground objects' bounds (seats with tables or seats left out) and
    between each ground object's bounds (corners and edge midpoints) and the walls; ``apex``: the tents' apexes, of
    the pairs and of the walls (:func:`apexes`); ``gaps_only``: the two tensors of gaps instead."""
    ground = torch.tensor(spec.ground_mask())[labels] & (labels != spec.empty_index)
    seat, table = (class_mask(labels, spec.classes, [name]) for name in ("seat", "table"))
    skip = (seat[:, :, None] & (seat | table)[:, None]) | (table[:, :, None] & seat[:, None])
    separation = geo.bounds_separations(trans, half, yaws)[..., 0:3:2]  # overlap (+) or minus the gap, per axis
    apart = (separation < 0).any(-1)
    pairs = (ground[:, :, None] & ground[:, None]).triu(1) & apart & ~skip
    gap = (-separation).clamp_min(0).norm(dim=-1).masked_fill(~pairs, 0.0)
    reach = footprint_reach(half[..., 0:3:2], torch.cos(yaws), torch.sin(yaws))
    points = trans[..., 0:3:2][:, :, None] + EDGE_POINTS.to(trans) * reach[:, :, None]  # (B, N, 8, 2)
    edges = floor_edges(floors).to(trans)
    to_walls = _point_segment_distance(points[:, :, :, None], edges[:, None, None, :, :2],
                                       edges[:, None, None, :, 2:]).amin(2)  # (B, N, E): each wall's nearest point
    to_walls = to_walls.masked_fill(~ground[..., None], 0.0)
    if gaps_only:
        return gap.detach(), to_walls.detach()
    return tent(gap, apex[0]).sum((1, 2)) + tent(to_walls, apex[1]).sum((1, 2))


def descend(batch: SceneBatch, weight: float, contact: dict | None, contact_gap_weight: float,
            relative: bool = False, steps: int = 300) -> torch.Tensor:
    """Translations of ``batch`` moved on the floor by ``steps`` steps of Adam down the penalty (module doc)."""
    trans0, half, yaws = batch.translations.double(), batch.half_sizes.double(), batch.yaws.double()
    valid = batch.labels != batch.spec.empty_index
    delta = torch.zeros(trans0.shape[:2] + (2,), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=DESCENT_LR)

    def moved(d: torch.Tensor) -> torch.Tensor:
        move = d * valid[..., None]
        return trans0 + torch.stack([move[..., 0], torch.zeros_like(move[..., 0]), move[..., 1]], -1)

    args = (half, yaws, batch.labels, batch.spec, batch.floors)
    apex = apexes(narrow_gaps(trans0, *args, gaps_only=True)) if relative else (2 * geo.AGENT_RADIUS,) * 2
    for _ in range(steps):
        trans = moved(delta)
        loss = layout_penalty(trans, half, yaws, batch.labels, batch.spec, batch.floors, out_of_bound_weight=20.0,
                              out_of_bound_shrink=0.0, contact=contact, overlap_measure="depth",
                              contact_gap_weight=contact_gap_weight, contact_gap=0.12)
        loss = loss + weight * narrow_gaps(trans, *args, apex=apex)
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
    parser.add_argument("--relative", action="store_true", help="a gap narrow in the room given is charged only "
                        "where it narrows further (the tent's apex: that gap)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    layouts = load_layouts(args.scenes, "diningroom")
    out = []
    for start in range(0, len(layouts), 50):
        batch = SceneBatch.from_layouts(layouts[start:start + 50])
        batch.translations = descend(batch, args.weight, None if args.charge_contact else SEAT_AT_TABLE,
                                     args.contact_gap_weight, args.relative)
        out += batch.to_layouts()
        print(f"{len(out)} of {len(layouts)} rooms", file=sys.stderr)
    save_layouts(out, args.out)


if __name__ == "__main__":
    main()
