"""Samplings of the same objects: each floor's classes drawn once by the prior (its own sampling, seed
``--classes-seed``), then ``--seeds`` samplings with those classes given at every step (as an adapter with required
objects samples). Their reports through ``research/best_of_floor_metrics.py`` tell how much a floor's arrangements of
one set of objects differ, the room a policy that keeps the classes (``adapt`` without ``class``) can draw on.

    .venv/bin/python research/same_objects_samplings.py --room diningroom --floors floors.json --out G [--seeds 0 1 2 3]
    iarcs evaluate --scenes G_S.json --reference floors.json --features none --out G_S_report.json   # each seed S
    .venv/bin/python research/best_of_floor_metrics.py G_0_report.json G_1_report.json ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.denoiser import ScenePrior, centre_floor  # noqa: E402
from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402

CHUNK = 100


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--room", required=True)
    parser.add_argument("--floors", required=True, help="a layout file whose floors to sample on")
    parser.add_argument("--out", required=True, help="the files' prefix: OUT_<seed>.json")
    parser.add_argument("--prior", help="a prior checkpoint (default: the shipped one of the room)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--classes-seed", type=int, default=100)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args(argv)
    prior = ScenePrior.load(args.prior) if args.prior else ScenePrior.load_default(args.room)
    floors = [centre_floor(layout.floor) for layout in load_layouts(args.floors, args.room)]
    generator = torch.Generator().manual_seed(args.classes_seed)
    with torch.no_grad():
        x0 = torch.cat([prior.sample_features(floors[i:i + CHUNK], args.steps, 1.0, generator)
                        for i in range(0, len(floors), CHUNK)])
    classes = x0[..., 8:].argmax(-1)
    for seed in tqdm(args.seeds, desc="samplings"):
        with torch.no_grad():
            scenes = prior.sample(floors, args.steps, 1.0, torch.Generator().manual_seed(seed), batch_size=CHUNK,
                                  classes=classes)
        save_layouts(scenes.to_layouts(), f"{args.out}_{seed}.json")


if __name__ == "__main__":
    main()
