"""Does the prior place a nightstand by its bed? Procedural bedrooms with one bed and a nightstand are noised to
t and restored in one step (x0_hat) twice, with the same noise: as they are, and with the bed's slot emptied
before noising. For the nightstands (those still decoded as nightstands both times) it prints the median error
to the truth each way, how far removing the bed moves them, and the quartiles of how far out from the true bed's
side they land. A network that places nightstands by their bed does worse without it.

    .venv/bin/python benchmarks/bed_ablation.py [--checkpoint PRIOR] [--num-scenes 500] [--seed 777] [--t 50 100 200]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from agents.denoiser import ScenePrior
from agents.pretrain_data import SceneTensors, encode_batch
from iarcs_env import relations as rel
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.scene import SceneBatch


def bed_ablation(prior: ScenePrior, rooms: list, timesteps, seed: int = 0) -> dict:
    """{t: figures} for the rooms of ``rooms`` with exactly one bed and at least one nightstand (module doc)."""
    spec = prior.spec
    data = SceneTensors.from_layouts(rooms, prior.num_slots)
    x0, floor = encode_batch(spec, prior.stats, *data.batch(torch.arange(len(data))))
    clean = SceneBatch.decode(x0, prior.stats, [lay.centred().floor for lay in rooms])
    bed = rel.class_mask(clean.labels, spec.classes, ["bed"])
    nightstand = rel.class_mask(clean.labels, spec.classes, ["nightstand"])
    keep = (bed.sum(1) == 1) & nightstand.any(1)
    x0, floor, bed, nightstand, clean = x0[keep], floor[keep], bed[keep], nightstand[keep], clean[keep]
    empty = torch.full((spec.num_classes,), -1.0)
    empty[spec.empty_index] = 1.0
    no_bed = x0.clone()
    no_bed[bed] = torch.cat([torch.zeros(x0.shape[-1] - spec.num_classes), empty])  # an empty slot, as encoded
    fn, schedule = prior.model_fn(floor.to(prior.device)), prior.schedule
    bed_slot = bed.float().argmax(1)
    rows = torch.arange(len(bed_slot))
    bed_xz, bed_half, bed_yaw = (clean.translations[rows, bed_slot][:, [0, 2]], clean.half_sizes[rows, bed_slot],
                                 clean.yaws[rows, bed_slot])
    out = {}
    for t in timesteps:
        noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(seed))
        tt = torch.full((x0.shape[0],), int(t))
        restored = []
        for x in (x0, no_bed):
            x_t = schedule.q_sample(x, tt, noise)
            with torch.no_grad():
                x0_hat = schedule.predict_x0(x_t, tt, fn(x_t.to(prior.device), tt.to(prior.device)).cpu())
            restored.append(SceneBatch.decode(x0_hat, prior.stats, clean.floors))
        sel = nightstand & (restored[0].labels == clean.labels) & (restored[1].labels == clean.labels)
        scene = torch.nonzero(sel)[:, 0]
        truth = clean.translations[..., 0:3:2][sel]
        with_bed, without = (r.translations[..., 0:3:2][sel] for r in restored)

        def out_from_side(p):  # metres out from the true bed's side, in its frame (negative: within its width)
            lateral = rel.local_offset(torch.stack([bed_xz[scene], p], 1), torch.stack([bed_yaw[scene]] * 2, 1))[:, 0, 1, 0]
            return (lateral.abs() - bed_half[scene, 0]).numpy()

        quartiles = lambda v: [float(q) for q in np.quantile(v, [0.25, 0.5, 0.75])] if len(v) else [np.nan] * 3
        out[int(t)] = {"rooms": int(keep.sum()), "nightstands": int(nightstand.sum()), "kept": int(sel.sum()),
                       "error_with_bed_m": float((with_bed - truth).norm(dim=-1).median()),
                       "error_without_bed_m": float((without - truth).norm(dim=-1).median()),
                       "moved_by_removing_bed_m": float((with_bed - without).norm(dim=-1).median()),
                       "out_from_side_truth": quartiles(out_from_side(truth)),
                       "out_from_side_with_bed": quartiles(out_from_side(with_bed)),
                       "out_from_side_without_bed": quartiles(out_from_side(without))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default=None, help="prior.pt (default: the shipped bedroom prior)")
    parser.add_argument("--num-scenes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=777, help="seed of the procedural rooms")
    parser.add_argument("--t", type=int, nargs="+", default=[50, 100, 200], help="noise levels")
    args = parser.parse_args()
    torch.set_num_threads(2)
    prior = ScenePrior.load(args.checkpoint) if args.checkpoint else ScenePrior.load_default("bedroom")
    rooms = [lay for lay in generate_layouts("bedroom", args.num_scenes, seed=args.seed) if len(lay) <= prior.num_slots]
    figures = bed_ablation(prior, rooms, args.t)
    q = lambda v: ", ".join(f"{x:+.2f}" for x in v)
    print("| t | nightstands (kept) | error, with the bed (m) | error, bed removed (m) | moved by removing the bed (m) "
          "| out from the side: truth | with the bed | bed removed |")
    print("|---:|---|---:|---:|---:|---|---|---|")
    for t, f in figures.items():
        print(f"| {t} | {f['kept']} of {f['nightstands']} | {f['error_with_bed_m']:.3f} | {f['error_without_bed_m']:.3f} | "
              f"{f['moved_by_removing_bed_m']:.3f} | {q(f['out_from_side_truth'])} | {q(f['out_from_side_with_bed'])} | "
              f"{q(f['out_from_side_without_bed'])} |")


if __name__ == "__main__":
    main()
