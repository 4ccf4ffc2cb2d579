"""Why chairs_at_dining_table holds or fails: in the rooms with a dining table and at least two chairs, the rate it
holds, chairs per room and at one table, and per chair the footprint gap to the nearest dining table (0: touching
or under it), the share within the relation's 0.6 m and the share of those facing the table
(``iarcs_env.relation_fidelity``'s tests), and the share standing ``PULLED_OUT`` m or more from their table (the data's
dining chairs never do; a chair pulled out that far closes the walkway behind it in a narrow room).

    .venv/bin/python research/chair_placement.py --room diningroom data=floors.json prior=prior.json run=S.json

``--chair dining_chair`` counts that class alone. ``--restore PRIOR --from-t 0 100`` (after the files) adds, under
each file, its rooms noised to each t and restored by PRIOR (20 DDIM steps, eta 1; t = 0: the chain's last step
alone): where a prior moves the chairs the data hands it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from iarcs_env import relation_fidelity as rf  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.metrics import batch_float64  # noqa: E402

PULLED_OUT = 0.15
"""m: a chair this far or farther from its nearest dining table counts as pulled out."""


def chair_placement(layouts, chunk: int = 100, chairs=rf.CHAIRS) -> dict:
    gaps, facing, counts, at_table = [], [], [], []
    for s in range(0, len(layouts), chunk):
        scenes = rf._Scenes(batch_float64(layouts[s:s + chunk]))
        table, chair = scenes.mask("dining_table"), scenes.mask(*chairs)
        pairs = scenes.pairs(table, chair)
        gap, looks = scenes.gap(pairs), scenes.looks_at(pairs)
        for k in range(len(table)):
            if not (table[k].any() and chair[k].sum() >= 2):
                continue
            counts.append(int(chair[k].sum()))
            at_table.append(int(((gap[k] <= rf.CHAIR_GAP + rf.EPS) & looks[k]).sum(1).max()))
            tables = table[k].nonzero().squeeze(1)
            for j in chair[k].nonzero().squeeze(1):
                i = tables[gap[k, tables, j].argmin()]
                gaps.append(float(gap[k, i, j]))
                facing.append(bool(looks[k, i, j]))
    if not counts:  # no room with a table and two of these chairs
        return dict.fromkeys(("holds", "chairs", "at_table", "touching", "pulled_out", "near", "facing_near",
                              "gap_median"), float("nan")) | {"rooms": 0}
    gaps, facing, near = np.array(gaps), np.array(facing), np.array(gaps) <= rf.CHAIR_GAP + rf.EPS
    return {"rooms": len(counts), "holds": float(np.mean(np.array(at_table) >= 2)), "chairs": float(np.mean(counts)),
            "at_table": float(np.mean(at_table)), "touching": float(np.mean(gaps <= 1e-6)),
            "pulled_out": float(np.mean(gaps >= PULLED_OUT)), "near": float(near.mean()),
            "facing_near": float(facing[near].mean()), "gap_median": float(np.median(gaps))}


@torch.no_grad()
def restored(layouts, prior, start: int, seed: int = 0) -> list:
    """``layouts`` noised to ``start`` (a step of the 20-step DDIM grid) and denoised by ``prior`` to t = 0."""
    from agents.pretrain_data import SceneTensors, encode_batch
    from eval_prior import denoise_chain
    from iarcs_env.scene import SceneBatch

    layouts = [lay for lay in layouts if len(lay) <= prior.num_slots]
    x0, floor = encode_batch(prior.spec, prior.stats, *SceneTensors.from_layouts(layouts, prior.num_slots).batch(
        torch.arange(len(layouts))))
    g = torch.Generator().manual_seed(seed)
    x = prior.schedule.q_sample(x0, start, torch.randn(x0.shape, generator=g))
    x = denoise_chain(prior, prior.model_fn(floor), x, start, 20, 1.0, g)
    return SceneBatch.decode(x, prior.stats, [lay.centred().floor for lay in layouts]).to_layouts()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--room", default="diningroom")
    ap.add_argument("--chair", action="append", help="count only these chair classes (default: the relation's)")
    ap.add_argument("--restore", metavar="PRIOR", help="a prior checkpoint that restores each file's rooms")
    ap.add_argument("--from-t", type=int, nargs="+", default=[0, 100], help="noise levels to restore from")
    ap.add_argument("files", nargs="+", help="NAME=FILE: neutral-JSON scene files of the room type")
    args = ap.parse_args(argv)
    prior = None
    if args.restore:
        from agents.denoiser import ScenePrior
        prior = ScenePrior.load(args.restore)
    print("| scenes | rooms with a table and 2+ chairs | holds | chairs / room | at one table | chairs touching "
          "their table | pulled out (>= 0.15 m) | within 0.6 m | of those facing it | median gap (m) |")
    print("|---|" + "---:|" * 9)
    for arg in args.files:
        name, _, path = arg.rpartition("=")
        name, layouts = name or Path(path).stem, load_layouts(path, args.room)
        rows = [(name, layouts)] + [(f"{name}, restored from t = {t}", restored(layouts, prior, t))
                                    for t in (args.from_t if prior else [])]
        for row, rooms in rows:
            c = chair_placement(rooms, chairs=args.chair or rf.CHAIRS)
            print(f"| {row} | {c['rooms']} | {c['holds']:.1%} | {c['chairs']:.2f} "
                  f"| {c['at_table']:.2f} | {c['touching']:.1%} | {c['pulled_out']:.1%} | {c['near']:.1%} "
                  f"| {c['facing_near']:.1%} | {c['gap_median']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
