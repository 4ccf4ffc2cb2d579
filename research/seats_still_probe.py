"""``iarcs`` with every seat and desk held still by the physics gradient's walkway term: their positions are
detached from :func:`iarcs_env.clearance.reach_clearance` inside :func:`agents.physics_gradient.layout_penalty`, so
the walkway term moves the other objects only (overlaps and walls still move seats and desks). A probe of why the
bedroom stage-1 adapter loses study_zone (docs/results/prior_bedroom_gpu.md, "Tried with the seat let be"), not a
project option.

    .venv/bin/python research/seats_still_probe.py train --config OVERRIDE.yaml
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

import agents.physics_gradient as physics_gradient  # noqa: E402
from experiments.cli import main  # noqa: E402
from iarcs_env.relations import class_mask  # noqa: E402

clearance, penalty = physics_gradient.reach_clearance, physics_gradient.layout_penalty
held = {}


def layout_penalty(trans, half, yaws, labels, spec, floors, **weights):
    held["mask"] = class_mask(labels, spec.classes, ["seat"]) | class_mask(labels, spec.classes, ["desk"])
    return penalty(trans, half, yaws, labels, spec, floors, **weights)


def reach_clearance(floors, trans, half, yaws, mask, radius):
    return clearance(floors, torch.where(held["mask"][..., None], trans.detach(), trans), half, yaws, mask, radius)


physics_gradient.layout_penalty, physics_gradient.reach_clearance = layout_penalty, reach_clearance

if __name__ == "__main__":
    main(sys.argv[1:])
