"""How well a scene prior (or an RL-tuned adapter) reproduces the object relations the paper's tasks are
about, next to its training data: beds with the headboard against a wall (and the median distance of
the headboard's midpoint from the wall behind it), where nightstands sit along the bed, beds per room, and
the five task success rates (hand-written checkers). two_nightstands is taken apart into its parts: rooms
with a bed and at least two nightstands, and the share of nightstands (in rooms with a bed, measured from
the nearest bed) that stand where the checker wants them, beside the head half within 0.5 m of the side,
with its two parts: 0 to 0.5 m out from the side, and along the head half; how far out from the side they
stand (quartiles; negative: within the bed's width); and how many of the nightstands next to a bed overlap it
(which the collision metric counts).

    .venv/bin/python research/relation_fidelity.py                       # prior and shipped stage 1
    .venv/bin/python research/relation_fidelity.py --runs out/train/task_two_nightstands
    .venv/bin/python research/relation_fidelity.py --priors out/pretrain/bedroom_small/prior.pt
    .venv/bin/python research/relation_fidelity.py --no-shipped --scenes prior=PRIOR.json real=REAL.json
"""

from __future__ import annotations

import argparse
import contextlib

import numpy as np
import torch

from iarcs_env import geometry as geo
from iarcs_env import relations as rel
from iarcs_env.datasets import load_layouts
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.env import default_floors
from iarcs_env.scene import SceneBatch
from iarcs_env.tasks import TASKS, along_head_half, out_from_side


def relation_row(scenes: SceneBatch) -> dict:
    """Relation statistics of a batch (see the module docstring)."""
    spec = scenes.spec
    bed = rel.class_mask(scenes.labels, spec.classes, ["bed"])
    nightstand = rel.class_mask(scenes.labels, spec.classes, ["nightstand"])
    edges = rel.floor_edges(scenes.floors, dtype=torch.float32)
    back = rel.back_to_wall(scenes.translations, scenes.half_sizes, scenes.yaws, edges)
    along = rel.local_offset(scenes.translations[..., 0:3:2], scenes.yaws)[..., 1] / scenes.half_sizes[..., 2][..., None]
    pairs = bed[:, :, None] & nightstand[:, None, :]
    quartiles = np.quantile(along[pairs].numpy(), [0.25, 0.5, 0.75]) if pairs.any() else [np.nan] * 3
    row = {"beds / room": float(bed.sum(1).float().mean()),
           "headboard at a wall %": 100 * float((back[bed] < 0.1).float().mean()) if bed.any() else np.nan,
           "headboard to wall, median (m)": float(back[bed].median()) if bed.any() else np.nan,
           "nightstand along bed (q1, median, q3)": ", ".join(f"{q:+.2f}" for q in quartiles),
           "bed and 2+ nightstands %": 100 * float((bed.any(1) & (nightstand.sum(1) >= 2)).float().mean()),
           **nightstands_beside_head(scenes, bed, nightstand),
           "nightstands at a bed overlapping it %": nightstands_overlapping_bed(scenes, bed, nightstand)}
    row.update({f"{name} %": 100 * float(np.mean(task.check(scenes))) for name, task in TASKS.items()})
    return row


def nightstands_beside_head(scenes: SceneBatch, bed: torch.Tensor, nightstand: torch.Tensor) -> dict:
    """Shares (%) of the nightstands in rooms with a bed whose centre, in the nearest bed's frame, lies where
    two_nightstands wants it (along the head half, 0 to 0.5 m out from the bed's side), and of each part."""
    keys = ("nightstands beside the head half %", "nightstands out from the side %", "nightstands along the head half %")
    gap_key = "nightstand out from the bed's side, m (q1, median, q3)"
    xz = scenes.translations[..., 0:3:2].double()
    offset = rel.local_offset(xz, scenes.yaws.double())  # [b, i, j]: j in i's frame
    nearest = rel.centre_distance(xz).masked_fill(~bed[:, :, None], float("inf")).argmin(1)  # [b, j] -> bed i
    b, j = torch.nonzero(nightstand & bed.any(1, keepdim=True), as_tuple=True)
    if len(b) == 0:
        return {**dict.fromkeys(keys, np.nan), gap_key: "-"}
    i = nearest[b, j]
    half = scenes.half_sizes[b, i].double()
    side = out_from_side(offset[b, i, j, 0], half[:, 0])
    along = along_head_half(offset[b, i, j, 1], half[:, 2])
    gap = offset[b, i, j, 0].abs() - half[:, 0]  # < 0: within the bed's width (ahead of or behind it)
    return {**{key: 100 * float(part.double().mean()) for key, part in zip(keys, (side & along, side, along))},
            gap_key: ", ".join(f"{q:+.2f}" for q in np.quantile(gap.numpy(), [0.25, 0.5, 0.75]))}


def nightstands_overlapping_bed(scenes: SceneBatch, bed: torch.Tensor, nightstand: torch.Tensor) -> float:
    """Share (%) of the bed-nightstand pairs with footprints at most 0.3 m apart whose boxes overlap (a
    collision of the Col_obj metric): the data tucks many nightstands slightly into the bed."""
    near = bed[:, :, None] & nightstand[:, None, :]
    near &= rel.footprint_gap(scenes.translations, scenes.half_sizes, scenes.yaws) <= 0.3
    if not near.any():
        return np.nan
    volume = geo.box_overlap_volumes(scenes.translations, scenes.half_sizes, scenes.yaws, scenes.ground_mask)
    return 100 * float((volume[near] > geo.COLLISION_VOLUME).double().mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num-scenes", type=int, default=256)
    parser.add_argument("--seed", type=int, default=777, help="seed of the held-out floors and the data rooms")
    parser.add_argument("--runs", nargs="*", default=[], help="training run folders whose adapters to add")
    parser.add_argument("--priors", nargs="*", default=[], help="other prior checkpoints (prior.pt) to add")
    parser.add_argument("--scenes", nargs="*", default=[], metavar="NAME=FILE",
                        help="layout files (iarcs sample output, or any dataset file) to add as rows as they are")
    parser.add_argument("--no-shipped", action="store_true", help="leave out the shipped prior's and stage 1's rows")
    args = parser.parse_args()
    torch.set_num_threads(1)
    from agents.denoiser import ScenePrior
    from agents.train import load_stage1_policy, load_trained_policy

    rows = {"procedural data": relation_row(SceneBatch.from_layouts(generate_layouts("bedroom", args.num_scenes,
                                                                                       seed=args.seed)))}
    floors = default_floors("bedroom", count=args.num_scenes, seed=args.seed)
    if not args.no_shipped:
        stage1 = load_stage1_policy("bedroom")
        for name, context in (("prior", stage1.base_policy), ("stage 1", contextlib.nullcontext)):
            with context():
                rows[name] = relation_row(stage1.sample(floors, generator=torch.Generator().manual_seed(0)))
    for path in args.priors:
        rows[path] = relation_row(ScenePrior.load(path).sample(floors, generator=torch.Generator().manual_seed(0),
                                                                 batch_size=64))
    for item in args.scenes:
        name, _, path = item.rpartition("=")
        rows[name or path] = relation_row(SceneBatch.from_layouts(load_layouts(path)))
    for run in args.runs:
        policy, _ = load_trained_policy(run)
        rows[run] = relation_row(policy.sample(floors, generator=torch.Generator().manual_seed(0)))
    keys = list(next(iter(rows.values())))
    print("| scenes | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for name, row in rows.items():
        print(f"| {name} | " + " | ".join(v if isinstance(v, str) else f"{v:.1f}" if "%" in k else f"{v:.2f}"
                                          for k, v in row.items()) + " |")


if __name__ == "__main__":
    main()
