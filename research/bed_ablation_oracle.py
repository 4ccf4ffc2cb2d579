"""How well could a denoiser restore a nightstand from t given its bed? A yardstick for the bed ablation's figure
(:mod:`agents.bed_ablation`: the median error of the one-step x0_hat, asked at most half the error without the bed
at t = 200). The procedural rooms put a bed's nightstands left or right of it at random, in random slot order, so
even a restoration that knows the bed exactly must tell the side from the nightstand's noisy position: this
posterior mean weighs each nightstand's true place against its mirror beside the other side of the bed by the
likelihood of the noised position (the room-frame scaling and noise of the shipped prior's schedule; two
nightstands beside one bed swap sides together) and reports its median error, and the same with the mirror ruled
out where it would leave the floor or hit other furniture.

    .venv/bin/python research/bed_ablation_oracle.py [--num-scenes 500] [--seed 777] [--t 50 100 200]

The oracle knows more than the network (the exact bed and where a nightstand goes beside it) and less (it ignores
other hints of the side, such as the bed's shift away from it), so it is a yardstick, not a bound.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-scenes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=777, help="seed of the procedural rooms (bed_ablation.py's)")
    parser.add_argument("--t", type=int, nargs="+", default=[50, 100, 200])
    parser.add_argument("--noise-draws", type=int, default=4)
    args = parser.parse_args()
    import numpy as np
    import torch

    from agents.denoiser import ScenePrior
    from iarcs_env import geometry as geo
    from iarcs_env import relations as rel
    from iarcs_env.datasets.procedural import generate_layouts
    from iarcs_env.scene import SceneBatch, floor_half_extents, translation_scale

    prior = ScenePrior.load_default("bedroom")
    spec = prior.spec
    rooms = [lay.centred() for lay in generate_layouts("bedroom", args.num_scenes, seed=args.seed)
             if len(lay) <= prior.num_slots]
    b = SceneBatch.from_layouts(rooms, num_slots=prior.num_slots)
    bed = rel.class_mask(b.labels, spec.classes, ["bed"])
    nightstand = rel.class_mask(b.labels, spec.classes, ["nightstand"])
    valid = b.labels != spec.empty_index
    # the room frame's scale of each object's x and z: its free half-range in the floor's box
    _, hi = translation_scale(prior.stats, b.translations, floor_half_extents(b.floors), b.half_sizes, b.yaws)
    free = hi[..., 0:3:2]
    errors = {t: ([], []) for t in args.t}  # (side told by the position only, blocked mirrors ruled out)
    blocked_share = []
    for i in torch.nonzero((bed.sum(1) == 1) & nightstand.any(1))[:, 0].tolist():
        j = int(bed[i].float().argmax())
        bed_xz, left = b.translations[i, j, 0:3:2], rel.left_xz(b.yaws[i, j][None])[0]
        places = []  # (slot, true xz, mirrored xz, mirror blocked)
        for k in torch.nonzero(nightstand[i])[:, 0].tolist():
            xz = b.translations[i, k, 0:3:2]
            mirror = xz - 2 * float((xz - bed_xz) @ left) * left
            moved = b.translations[i].clone()
            moved[k, 0], moved[k, 2] = mirror[0], mirror[1]
            outside = geo.box_out_of_floor_area(moved[None], b.half_sizes[i][None], b.yaws[i][None], [b.floors[i]],
                                                valid[i][None], geo.OUT_OF_BOUND_SHRINK)[0, k] > geo.OUT_OF_BOUND_AREA
            overlap = geo.bounds_separations(moved[None], b.half_sizes[i][None], b.yaws[i][None])[0, k]
            others = valid[i] & ~nightstand[i]
            others[j] = False
            hits = ((overlap.clamp_min(0).prod(-1) > 1e-3) & others).any()
            places.append((k, xz, mirror, bool(outside or hits)))
        beside = [p for p in places if abs(float((p[1] - bed_xz) @ left)) < 2.0]
        groups = [beside] if len(beside) == 2 else [[p] for p in places]
        blocked_share += [p[3] for p in places]
        for t in args.t:
            abar = float(prior.schedule.alphas_cumprod[t])
            for draw in range(args.noise_draws):
                gen = torch.Generator().manual_seed(1000 * draw + i)
                for group in groups:
                    log_odds, blocked = 0.0, False
                    for k, xz, mirror, bad in group:  # noised room-frame position, scored at both places
                        y = math.sqrt(abar) * xz / free[i, k] + math.sqrt(1 - abar) * torch.randn(2, generator=gen)
                        dist = lambda at: float(((y - math.sqrt(abar) * at / free[i, k]) ** 2).sum())
                        log_odds += (dist(mirror) - dist(xz)) / (2 * (1 - abar))
                        blocked |= bad
                    wrong = 1 / (1 + math.exp(min(log_odds, 50)))  # the mirror's posterior weight
                    for k, xz, mirror, _ in group:
                        errors[t][0].append(wrong * float((xz - mirror).norm()))
                        errors[t][1].append(0.0 if blocked else wrong * float((xz - mirror).norm()))
    print(f"{len(blocked_share)} nightstands; the mirror leaves the floor or hits furniture for "
          f"{100 * np.mean(blocked_share):.0f}% of them")
    print("| t | posterior-mean error given the bed: median (mean), m | blocked mirrors ruled out: median (mean), m |")
    print("|---:|---:|---:|")
    for t, (told, walls) in errors.items():
        print(f"| {t} | {np.median(told):.3f} ({np.mean(told):.3f}) | {np.median(walls):.3f} ({np.mean(walls):.3f}) |")


if __name__ == "__main__":
    main()
