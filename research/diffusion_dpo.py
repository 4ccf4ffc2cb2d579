"""Preferences instead of targets: Diffusion-DPO (Wallace et al., 2023) from the task checker. Where the fine-tuning of
``search_sft.py`` regresses the adapter onto the searched rooms, and so also moves it where nothing was wrong (it undoes
the task gradient: stage2_tasks.md, "What the fine-tuning costs"), DPO only asks the adapter to denoise a passing room
better, and a failing room of the same floor worse, than its frozen start (the reference) does:

    L = -log sigmoid(-beta * [(e(w) - e_ref(w)) - (e(l) - e_ref(l))])

e the weighted mean square of x0_hat against the room (its adapted features), both rooms noised to the same timestep
with the same noise. The pairs (one a training floor): ``--pairs searched``, the winner is the adapter's own room
rearranged by the layout search (``layout_search.py``) and the loser that room as sampled, kept when the winner passes
cleanly and the loser fails; ``--pairs own``, ``--per-floor`` of the adapter's own rooms, a clean pass against a
failure of the same floor (as many pairs as the floor has of the rarer kind). Success is measured as
``search_sft.py`` measures it (``--other-floors`` held-out floors of seed 4242). Writes a run folder that ``iarcs
sample --checkpoint`` and a config's ``init_adapter`` read.

    .venv/bin/python research/diffusion_dpo.py experiments/ablations/task_wheelchair_gradient.yaml --task wheelchair \\
        --init RUN --pairs searched --rooms 1024 --margin 0.1 --steps 500 --beta 100 --cache PAIRS.pt --out RUN2
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from layout_search import search_rooms  # noqa: E402
from search_sft import (CHUNK, FIELDS, HELD_OUT_SEED, cat, held_out_report, procedural_floors, success,  # noqa: E402
                        task_policy)
from self_distill import clean_passes  # noqa: E402
from agents.physics_gradient import adapted_object_weights  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402


def searched_pairs(policy, floors, task: str, generator, margin: float) -> tuple[SceneBatch, SceneBatch, list[int]]:
    """(winners, losers, their floors' indices): the policy's room of each floor searched, against it as sampled, where
    only the search passes."""
    wins, losses, index = [], [], []
    for i in tqdm(range(0, len(floors), CHUNK), desc="rooms sampled and searched", unit="chunk"):
        with torch.no_grad():
            sampled = policy.sample(floors[i:i + CHUNK], generator)
        searched = search_rooms(sampled, task, margin=margin)
        keep = np.nonzero(clean_passes(searched, task) & ~clean_passes(sampled, task))[0]
        wins.append(searched[keep])
        losses.append(sampled[keep])
        index += [i + int(j) for j in keep]
    return cat(wins), cat(losses), index


def own_pairs(policy, floors, per_floor: int, task: str, generator) -> tuple[SceneBatch, SceneBatch, list[int]]:
    """(winners, losers, their floors' indices): ``per_floor`` of the policy's rooms a floor, each clean pass paired
    with a failure of its floor."""
    wins, losses, index = [], [], []
    for i in tqdm(range(0, len(floors), CHUNK), desc="rooms sampled and checked", unit="chunk"):
        part = [f for f in floors[i:i + CHUNK] for _ in range(per_floor)]
        with torch.no_grad():
            batch = policy.sample(part, generator)
        ok = clean_passes(batch, task).reshape(-1, per_floor)
        w, l_ = [], []
        for floor, passed in enumerate(ok):
            good, bad = np.nonzero(passed)[0], np.nonzero(~passed)[0]
            pairs = min(len(good), len(bad))
            w += [floor * per_floor + int(j) for j in good[:pairs]]
            l_ += [floor * per_floor + int(j) for j in bad[:pairs]]
            index += [i + floor] * pairs
        wins.append(batch[np.asarray(w, dtype=np.int64)])
        losses.append(batch[np.asarray(l_, dtype=np.int64)])
    return cat(wins), cat(losses), index


def per_room_square(policy, x0, x_t, t, cond, classes, weight) -> torch.Tensor:
    """(B,) the weighted mean square of the policy's x0_hat from ``x_t`` against ``x0``."""
    pred = policy.predict_x0(x_t, t, cond, classes, straight_through=True)
    return ((pred - x0).square() * weight).sum((1, 2)) / weight.sum((1, 2)).clamp_min(1)


def dpo_train(policy, reference, wins: SceneBatch, losses: SceneBatch, steps: int, lr: float, beta: float,
              generator: torch.Generator, every: int, report, batch: int = 64) -> None:
    """``steps`` Adam steps of the DPO loss (module doc) on ``batch`` pairs each, the timestep uniform."""
    prior = policy.prior
    data = []
    for rooms in (wins, losses):
        x0 = rooms.encode(prior.stats)
        data.append((x0, prior.floor_condition(rooms.floors), rooms.labels, adapted_object_weights(policy, x0)))
    params = policy.trainable_parameters()
    optimizer = torch.optim.Adam(params, lr=lr)
    policy.model.eval()
    log = {"loss": [], "accuracy": [], "margin": []}
    for step in tqdm(range(1, steps + 1), desc="DPO on the pairs", unit="step"):
        pick = torch.randint(0, len(wins), (batch,), generator=generator)
        t = torch.randint(0, prior.schedule.num_train_timesteps, (batch,), generator=generator)
        noise = torch.randn((batch, *data[0][0].shape[1:]), generator=generator)
        gaps = []
        for x0, cond, labels, weight in data:
            x0, cond, labels, weight = x0[pick], cond[pick], labels[pick], weight[pick]
            x_t = prior.with_classes(prior.schedule.q_sample(x0, t, noise), t, labels, generator)
            with torch.no_grad():
                ref = per_room_square(reference, x0, x_t, t, cond, labels, weight)
            gaps.append(per_room_square(policy, x0, x_t, t, cond, labels, weight) - ref)
        margin = gaps[0] - gaps[1]
        loss = -F.logsigmoid(-beta * margin).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        log["loss"].append(loss.item())
        log["accuracy"].append((margin < 0).float().mean().item())
        log["margin"].append(margin.mean().item())
        if step % every == 0 or step == steps:
            tqdm.write(f"step {step}: winner preferred {np.mean(log['accuracy']):.1%}, margin "
                       f"{np.mean(log['margin']):+.5f}")
            report(step, np.mean(log["loss"]))  # the DPO loss and the held-out success
            log = {k: [] for k in log}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a task training config (room, prior, adapt, required_objects)")
    parser.add_argument("--task", required=True, help="the task checker that makes the preferences")
    parser.add_argument("--init", help="a run folder whose adapter is the start and the reference (default: the "
                        "config's init_adapter)")
    parser.add_argument("--pairs", choices=["searched", "own"], default="searched")
    parser.add_argument("--rooms", type=int, default=1024, help="training floors")
    parser.add_argument("--per-floor", type=int, default=4, help="rooms a floor (--pairs own)")
    parser.add_argument("--margin", type=float, default=0.0, help="the search's margin (m; --pairs searched)")
    parser.add_argument("--floor-seed", type=int, help="the training floors' seed (default: the config's)")
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--batch", type=int, default=64, help="pairs a step")
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--beta", type=float, default=100.0)
    parser.add_argument("--eval-every", type=int, default=100)
    parser.add_argument("--other-floors", type=int, default=64)
    parser.add_argument("--cache", help="a file for the pairs: written once, then read")
    parser.add_argument("--out", help="write a run folder with the adapter")
    args = parser.parse_args(argv)
    cfg, policy = task_policy(args.config, args.init)
    reference = copy.deepcopy(policy)
    for p in reference.parameters():
        p.requires_grad_(False)
    generator = torch.Generator().manual_seed(cfg.seed)
    seed = cfg.floor_seed if args.floor_seed is None else args.floor_seed
    floors = procedural_floors(cfg.room, args.rooms, seed)
    if args.cache and Path(args.cache).exists():
        saved = torch.load(args.cache)
        index = saved["floor_index"]
        wins, losses = (SceneBatch(policy.prior.spec, *(saved[side][k] for k in FIELDS), [floors[i] for i in index])
                        for side in ("wins", "losses"))
    else:
        if args.pairs == "searched":
            wins, losses, index = searched_pairs(policy, floors, args.task, generator, args.margin)
        else:
            wins, losses, index = own_pairs(policy, floors, args.per_floor, args.task, generator)
        if args.cache:
            torch.save({"floor_index": index, **{side: {k: getattr(rooms, k) for k in FIELDS}
                                                  for side, rooms in (("wins", wins), ("losses", losses))}}, args.cache)
    if not len(wins):
        raise SystemExit(f"no pair: no floor had both a clean pass and a failure of {args.task}; sample more floors")
    print(f"{len(wins)} pairs on {len(set(index))} of {len(floors)} floors", flush=True)
    other = procedural_floors(cfg.room, args.other_floors, HELD_OUT_SEED)
    print(f"step 0: {args.task} on {len(other)} other floors {success(policy, other, args.task):.1%}", flush=True)
    dpo_train(policy, reference, wins, losses, args.steps, args.lr, args.beta, generator, args.eval_every,
              held_out_report(policy, cfg, args.task, other, args.out), args.batch)


if __name__ == "__main__":
    main()
