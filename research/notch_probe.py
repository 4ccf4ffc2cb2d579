"""Does the prior see a floor's notches? Each non-rectangular floor of a layout file sampled as it is and as its
bounding rectangle, with the same noise; printed both ways: the objects out of bound of the true floor (R_out's
definition). Were the floor encoder blind to notches, the two would match (``docs/results/augmentation.md``).

    .venv/bin/python research/notch_probe.py FLOORS.json [--checkpoint PRIOR] [--repeats 16]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.denoiser import ScenePrior, centre_floor  # noqa: E402
from iarcs_env import geometry as geo  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.floorplan import FloorPlan  # noqa: E402


def bounding_rectangle(floor: FloorPlan) -> FloorPlan:
    """The axis-aligned rectangle around ``floor`` (same centre, so the prior's frame does not move)."""
    (x0, z0), (x1, z1) = floor.vertices.min(0), floor.vertices.max(0)
    return FloorPlan.from_vertices([(x0, z0), (x1, z0), (x1, z1), (x0, z1)])


def out_of_true_floor(prior: ScenePrior, floors: list[FloorPlan], conditioned_on: list[FloorPlan],
                      seed: int = 0) -> tuple[int, int]:
    """(objects out of bound of ``floors``, objects) of the prior's samples conditioned on ``conditioned_on``."""
    b = prior.sample(conditioned_on, generator=torch.Generator().manual_seed(seed), batch_size=256)
    area = geo.box_out_of_floor_area(b.translations, b.half_sizes, b.yaws, [centre_floor(f) for f in floors], b.mask,
                                     geo.OUT_OF_BOUND_SHRINK)
    return int(((area > geo.OUT_OF_BOUND_AREA) & b.mask).sum()), int(b.mask.sum())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("floors", help="a layout file (its floor plans)")
    p.add_argument("--room", default="bedroom")
    p.add_argument("--checkpoint", help="prior.pt (default: the shipped prior)")
    p.add_argument("--repeats", type=int, default=16, help="samplings per floor")
    args = p.parse_args(argv)
    prior = ScenePrior.load(args.checkpoint) if args.checkpoint else ScenePrior.load_default(args.room)
    floors = [lay.floor for lay in load_layouts(args.floors, args.room, num_scenes=0) if not lay.floor.is_rectangle]
    true = [f for f in floors for _ in range(args.repeats)]
    for name, cond in (("as it is", true), ("as its bounding rectangle", [bounding_rectangle(f) for f in true])):
        out, n = out_of_true_floor(prior, true, cond)
        print(f"{len(floors)} non-rectangular floors x {args.repeats}, sampled {name}: {out} of {n} objects out of "
              f"the true floor ({100 * out / n:.2f}%)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
