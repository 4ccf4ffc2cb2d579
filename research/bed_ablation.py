"""Does the prior place a nightstand by its bed? :func:`agents.bed_ablation.bed_ablation` on procedural bedrooms
with one bed and a nightstand, printed as a Markdown table (see that module for what the figures are).

    .venv/bin/python research/bed_ablation.py [--checkpoint PRIOR] [--num-scenes 500] [--seed 777] [--t 50 100 200]
        [--noise-draws 4] [--noise-seed 0]

``--noise-draws 1 --noise-seed S`` gives one draw's figures (draw S of the pooled four).
"""

from __future__ import annotations

import argparse

import torch

from agents.bed_ablation import bed_ablation
from agents.denoiser import ScenePrior
from iarcs_env.datasets.procedural import generate_layouts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default=None, help="prior.pt (default: the shipped bedroom prior)")
    parser.add_argument("--num-scenes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=777, help="seed of the procedural rooms")
    parser.add_argument("--t", type=int, nargs="+", default=[50, 100, 200], help="noise levels")
    parser.add_argument("--noise-draws", type=int, default=4, help="noise draws pooled")
    parser.add_argument("--noise-seed", type=int, default=0, help="seed of the first noise draw")
    args = parser.parse_args()
    torch.set_num_threads(2)
    prior = ScenePrior.load(args.checkpoint) if args.checkpoint else ScenePrior.load_default("bedroom")
    rooms = [lay for lay in generate_layouts("bedroom", args.num_scenes, seed=args.seed) if len(lay) <= prior.num_slots]
    figures = bed_ablation(prior, rooms, args.t, seed=args.noise_seed, noise_draws=args.noise_draws)
    q = lambda v: ", ".join(f"{x:+.2f}" for x in v)
    print(f"| t | nightstands (kept, {args.noise_draws} noise draws) | error, with the bed (m) "
          "| error, bed removed (m) | ratio "
          "| moved by removing the bed (m) | the bed's own error (m) | error in the restored bed's frame (m) "
          "| out from the side: truth | with the bed | bed removed |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---|---|---|")
    for t, f in figures.items():
        print(f"| {t} | {f['kept']} of {f['nightstands'] * f['noise_draws']} | {f['error_with_bed_m']:.3f} | "
              f"{f['error_without_bed_m']:.3f} | {f['ratio']:.2f} | "
              f"{f['moved_by_removing_bed_m']:.3f} | {f['bed_error_m']:.3f} | {f['error_from_restored_bed_m']:.3f} | "
              f"{q(f['out_from_side_truth'])} | {q(f['out_from_side_with_bed'])} | "
              f"{q(f['out_from_side_without_bed'])} |")


if __name__ == "__main__":
    main()
