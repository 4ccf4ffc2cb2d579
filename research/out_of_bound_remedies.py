"""What a training config's composite reward pays for each way of taking an object out of the walls.

    .venv/bin/python research/out_of_bound_remedies.py experiments/stage1_bedroom_quick.yaml out/eval/X/base_s0.json

For every object of the scene files that is out of bound (R_out's definition), three edits of its scene are
scored with the config's reward against the scene as it is: **moved** (the smallest shift, on a 2 cm grid
within 1.5 m, that brings it inside; objects no shift brings in are left out), **shrunk** (its footprint
scaled down in 2% steps until it is inside; its height kept) and **deleted**. Printed per edit: the mean
change of the weighted total, the share of edits it improves, and the mean change of each weighted term.
DDPO climbs whichever edit pays most and is easiest to reach: when shrinking pays as well as moving, the
adapter shrinks the furniture (``footprint_change`` in ``iarcs evaluate --reference``).

The terms that score a scene against its batch (``class_frequency``, ``object_size``, the ``match`` modes)
see each edited scene in a batch of all the given scenes plus the edited ones, as a training batch would
see a scene in which one object changed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iarcs_env import geometry as geo  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402

EDITS = ("moved", "shrunk", "deleted")


def _out_area(translations, half_sizes, yaws, floor) -> torch.Tensor:
    """Out-of-floor area (R_out's shrink) of n candidate boxes on one floor."""
    n = len(translations)
    return geo.box_out_of_floor_area(translations[:, None], half_sizes[:, None], yaws[:, None], [floor] * n,
                                     torch.ones(n, 1, dtype=torch.bool), geo.OUT_OF_BOUND_SHRINK)[:, 0]


def _appended(batch: SceneBatch, more: SceneBatch) -> SceneBatch:
    return SceneBatch(batch.spec, torch.cat([batch.labels, more.labels]),
                      torch.cat([batch.translations, more.translations]), torch.cat([batch.half_sizes, more.half_sizes]),
                      torch.cat([batch.yaws, more.yaws]), batch.floors + more.floors)


def remedies(batch: SceneBatch, step: float = 0.02, reach: float = 1.5) -> dict:
    """``{"objects": [(scene, slot)], "original": SceneBatch, edit: (SceneBatch, ok mask)}``: one scene per
    out-of-bound object, as it is and with each edit applied to that object alone."""
    area = geo.box_out_of_floor_area(batch.translations, batch.half_sizes, batch.yaws, batch.floors, batch.mask,
                                     geo.OUT_OF_BOUND_SHRINK)
    objects = [tuple(ix) for ix in torch.nonzero(area > geo.OUT_OF_BOUND_AREA).tolist()]
    rows = [s for s, _ in objects]
    grid = torch.arange(-reach, reach + step / 2, step, dtype=batch.translations.dtype)
    shifts = torch.stack(torch.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    shifts = shifts[shifts.norm(dim=1).argsort()]
    scales = torch.arange(0.98, 0.299, -0.02, dtype=batch.half_sizes.dtype)
    edited = {name: batch[rows] for name in EDITS}  # copies: a scene per out-of-bound object
    ok = {name: np.zeros(len(objects), bool) for name in EDITS}
    for k, (s, o) in enumerate(objects):
        t, h, yaw = batch.translations[s, o], batch.half_sizes[s, o], batch.yaws[s, o]
        moved = t.repeat(len(shifts), 1)
        moved[:, [0, 2]] += shifts
        inside = torch.nonzero(_out_area(moved, h.repeat(len(shifts), 1), yaw.repeat(len(shifts)), batch.floors[s])
                               <= geo.OUT_OF_BOUND_AREA)
        if len(inside):
            edited["moved"].translations[k, o] = moved[inside[0, 0]]
            ok["moved"][k] = True
        smaller = h.repeat(len(scales), 1)
        smaller[:, [0, 2]] *= scales[:, None]
        inside = torch.nonzero(_out_area(t.repeat(len(scales), 1), smaller, yaw.repeat(len(scales)), batch.floors[s])
                               <= geo.OUT_OF_BOUND_AREA)
        if len(inside):
            edited["shrunk"].half_sizes[k, o] = smaller[inside[0, 0]]
            ok["shrunk"][k] = True
        edited["deleted"].labels[k, o] = batch.spec.empty_index
        ok["deleted"][k] = True
    return {"objects": objects, "original": batch[rows],
            **{name: (edited[name], ok[name]) for name in EDITS}}


def score(reward, batch: SceneBatch, found: dict) -> dict:
    """Per edit: mean change of the weighted total, share of edits it improves, and each weighted term's mean
    change, over the edits that could be made; every scene scored in a batch of ``batch`` plus the edited ones."""
    def scored(scenes: SceneBatch):
        total, terms = reward(_appended(batch, scenes))
        return total[len(batch):], {k: v[len(batch):] for k, v in terms.items()}

    total0, terms0 = scored(found["original"])
    out = {}
    for name in EDITS:
        edited, ok = found[name]
        total, terms = scored(edited)
        change = (total - total0).numpy()[ok]
        out[name] = {"n": int(ok.sum()), "total": float(change.mean()) if ok.any() else float("nan"),
                     "improved": float((change > 0).mean()) if ok.any() else float("nan"),
                     "terms": {k: float((reward.weights[k] * (terms[k] - terms0[k])).numpy()[ok].mean())
                               for k in terms}}
    return out


def main(argv=None) -> int:
    from agents.train import build_prior, load_train_config
    from rewards.composite import CompositeReward

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="a training config (its reward: and prior:)")
    p.add_argument("scenes", nargs="+", help="neutral-JSON scene files (e.g. the prior's samples)")
    args = p.parse_args(argv)
    cfg = load_train_config(args.config)
    reward = CompositeReward.from_config(cfg.reward, stats=build_prior(cfg).stats)
    batch = SceneBatch.from_layouts([lay for f in args.scenes for lay in load_layouts(f, num_scenes=0)])
    found = remedies(batch)
    if not found["objects"]:
        print(f"no object out of bound in {len(batch)} scenes")
        return 0
    result = score(reward, batch, found)
    names = list(next(iter(result.values()))["terms"])
    print(f"{len(found['objects'])} objects out of bound in {len(batch)} scenes; reward of {args.config}\n")
    print("| edit | objects | total change | improved | " + " | ".join(names) + " |\n|---|" + "---:|" * (3 + len(names)))
    for name, r in result.items():
        print(f"| {name} | {r['n']} | {r['total']:+.2f} | {100 * r['improved']:.0f}% | "
              + " | ".join(f"{r['terms'][k]:+.2f}" for k in names) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
