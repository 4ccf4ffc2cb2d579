"""Does an adapter learn from its own rooms? The adapter of ``--init`` samples ``--per-floor`` rooms on each of
``--rooms`` training floors and is fine-tuned on them as ``search_sft.py`` fine-tunes on searched rooms (x0_hat
regressed onto each room at a uniform timestep, or one in ``--t-range``). ``--keep passing``: only the rooms that pass
the task with no object outside the walls or off the floor, expert iteration with the policy as its own expert
(rejection-sampling fine-tuning); its own rooms lie where it samples, where the searched rooms do not. ``--keep all``:
every room, the control that tells what the fine-tuning itself does to an adapter (on its own samples it should move
nothing). Writes a run folder that ``iarcs sample --checkpoint`` and a config's ``init_adapter`` read.

    .venv/bin/python research/self_distill.py experiments/ablations/task_wheelchair_gradient.yaml --task wheelchair \\
        --init RUN --rooms 1024 --per-floor 4 --keep passing --steps 750 --cache ROOMS.pt --out RUN2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from search_sft import (CHUNK, FIELDS, HELD_OUT_SEED, cat, fine_tune, held_out_report, procedural_floors,  # noqa: E402
                        success, task_policy)
from iarcs_env.metrics import evaluate_batch  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402


def clean_passes(rooms: SceneBatch, task: str) -> np.ndarray:
    """(B,) rooms that pass ``task`` with no object outside the walls (R_out) or off the floor (R_off_floor)."""
    res = evaluate_batch(rooms)
    return task_results(task, rooms) & ~res.out_of_bound.any(1) & ~res.off_floor.any(1)


def own_rooms(policy, floors: list, per_floor: int, task: str, generator, passing: bool
              ) -> tuple[SceneBatch, list[int]]:
    """The policy's rooms on ``floors`` (``per_floor`` each), with ``passing`` only those that :func:`clean_passes`,
    and their floors' indices."""
    kept, index = [], []
    for i in tqdm(range(0, len(floors), CHUNK), desc="rooms sampled and checked", unit="chunk"):
        part = [f for f in floors[i:i + CHUNK] for _ in range(per_floor)]
        with torch.no_grad():
            batch = policy.sample(part, generator)
        keep = np.nonzero(clean_passes(batch, task) if passing else np.ones(len(batch), bool))[0]
        kept.append(SceneBatch(batch.spec, *(getattr(batch, k)[keep] for k in FIELDS), [part[j] for j in keep]))
        index += [i + int(j) // per_floor for j in keep]
    return cat(kept), index


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a task training config (room, prior, adapt, required_objects)")
    parser.add_argument("--task", required=True, help="the task checker that picks the rooms")
    parser.add_argument("--init", required=True, help="a run folder (search_sft.py --out, iarcs train) whose adapter "
                        "samples the rooms and is fine-tuned")
    parser.add_argument("--rooms", type=int, default=1024, help="training floors")
    parser.add_argument("--per-floor", type=int, default=4, help="rooms sampled on each floor")
    parser.add_argument("--keep", choices=["passing", "all"], default="passing",
                        help="the rooms to fine-tune on: those that pass cleanly, or every one (the control)")
    parser.add_argument("--floor-seed", type=int, help="the training floors' seed (default: the config's)")
    parser.add_argument("--steps", type=int, default=750)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--eval-every", type=int, default=250)
    parser.add_argument("--other-floors", type=int, default=64)
    parser.add_argument("--t-range", type=int, nargs=2, metavar=("LO", "HI"),
                        help="fine-tune at timesteps in [LO, HI) only (default: all)")
    parser.add_argument("--cache", help="a file for the kept rooms: written once, then read")
    parser.add_argument("--out", help="write a run folder with the fine-tuned adapter")
    args = parser.parse_args(argv)
    cfg, policy = task_policy(args.config, args.init)
    generator = torch.Generator().manual_seed(cfg.seed)
    seed = cfg.floor_seed if args.floor_seed is None else args.floor_seed
    if args.cache and Path(args.cache).exists():
        fields = torch.load(args.cache)
        floors = procedural_floors(cfg.room, fields["num_floors"], fields["floor_seed"])
        rooms = SceneBatch(policy.prior.spec, *(fields[k] for k in FIELDS), [floors[i] for i in fields["floor_index"]])
        index = fields["floor_index"]
    else:
        rooms, index = own_rooms(policy, procedural_floors(cfg.room, args.rooms, seed), args.per_floor, args.task,
                                 generator, args.keep == "passing")
        if args.cache:
            torch.save({"floor_seed": seed, "num_floors": args.rooms, "floor_index": index,
                        **{k: getattr(rooms, k) for k in FIELDS}}, args.cache)
    if not len(rooms):
        raise SystemExit(f"no room passed {args.task} cleanly: sample more floors (--rooms) or more rooms a floor "
                         "(--per-floor)")
    print(f"{len(rooms)} rooms kept on {len(set(index))} floors: {args.task} "
          f"{task_results(args.task, rooms).mean():.1%}")
    other = procedural_floors(cfg.room, args.other_floors, HELD_OUT_SEED)
    print(f"step 0: {args.task} on {len(other)} other floors {success(policy, other, args.task):.1%}", flush=True)
    fine_tune(policy, rooms, policy.trainable_parameters(), args.steps, args.lr, generator, args.eval_every,
              held_out_report(policy, cfg, args.task, other, args.out), args.batch, args.t_range)


if __name__ == "__main__":
    main()
