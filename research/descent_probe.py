"""Can a network predict the descent's move from the room at all? The rooms of ``research/descent_offline.py``'s
cache files: each room's last-step state x_t, the prior's prediction x0_hat from it, and the descent's move of that
room. Scored on the rooms of ``--held-out`` (a cache file of other floors) by the share of the move's mean square
they explain (1 - miss / move, over the objects present and the adapted features):

- ``--run``: the adapter of a ``descent_offline.py --out`` run, whose move is its x0_hat minus the prior's;
- the denoiser's own architecture trained from scratch on the ``--cache`` rooms (the run's) to output the move from
  the clean room x0_hat (t = 0) and the floor, ``--epochs`` passes.

The adapter explaining little where the fresh network explains much: the prior's features, not the rooms, limit
what the adapter learns. The adapter explaining more (measured: docs/results/stage1_living_dining.md): the prior's
features help, and the number of rooms is what limits it.

    .venv/bin/python research/descent_probe.py experiments/ablations/stage1_livingroom_descent.yaml \
        --cache ROOMS.pt --held-out OTHER.pt --run RUN --lora-targets REGEX --epochs 10 [--held-out-floor-seed S]

With ``--held-out`` one of the ``--cache`` files and ``--held-out-floor-seed`` its config's floor seed, it scores
how well the run fits the rooms it trained on, and what that fit does to their collisions and walkways.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling script

from agents.denoiser import SceneDenoiser  # noqa: E402
from agents.physics_gradient import adapted_object_weights  # noqa: E402
from agents.train import ADAPTERS_DIR, load_train_config  # noqa: E402
from descent_offline import build_with_targets, explained, load_rooms, predictions  # noqa: E402
from iarcs_env.datasets.procedural import generate_layouts  # noqa: E402
from iarcs_env.metrics import evaluate_layouts  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="the descent-imitation config the cache files were made with")
    parser.add_argument("--cache", action="append", required=True,
                        help="a descent_offline.py cache file the run trained on (more than one: their rooms together)")
    parser.add_argument("--held-out", required=True, help="a cache file of other floors")
    parser.add_argument("--run", help="a descent_offline.py --out folder whose adapter to score")
    parser.add_argument("--lora-targets", help="the run's --lora-targets")
    parser.add_argument("--held-out-floor-seed", type=int,
                        help="the floor seed the --held-out file was made with: also the Col_obj and R_reach of its rooms "
                             "as the prior made them, descended, and (with --run) as the adapter makes them")
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--lr", type=float, default=1e-3)
    args = parser.parse_args(argv)
    cfg = load_train_config(args.config)
    _, policy = build_with_targets(cfg, args.lora_targets)
    prior = policy.prior
    trained_on, held_out = load_rooms(args.cache), load_rooms([args.held_out])
    x_in, cond, target = (torch.cat(pair) for pair in zip(trained_on, held_out))
    held_count = len(held_out[0])
    del trained_on, held_out
    with policy.base_policy():
        x0 = predictions(policy.predict_x0, x_in, cond).clamp(-1, 1)
    move = target - x0
    weight = adapted_object_weights(policy, target)
    generator = torch.Generator().manual_seed(0)
    train, held = torch.arange(len(x_in) - held_count), torch.arange(len(x_in) - held_count, len(x_in))
    print(f"{len(train)} rooms to train on, {len(held)} held out; the move's mean square "
          f"{float((move.square() * weight).sum() / weight.sum()):.5f} per adapted feature")

    def score(move_of, rows) -> float:  # the share explained of the rooms ``rows``' move
        return explained(move_of(rows), move[rows], weight[rows])

    def adapter_move(rows):
        return predictions(policy.predict_x0, x_in[rows], cond[rows]).clamp(-1, 1) - x0[rows]

    seen = train[:len(held)]
    if args.run:
        policy.load_adapter(Path(args.run) / ADAPTERS_DIR / cfg.adapter, cfg.adapter)
        print(f"the adapter of {args.run}: explains {score(adapter_move, held):.1%} of the held-out rooms' move, "
              f"{score(adapter_move, seen):.1%} of as many trained-on rooms'")
    if args.held_out_floor_seed is not None:
        floors = [lay.centred().floor for lay in generate_layouts(cfg.room, held_count, seed=args.held_out_floor_seed)]
        rooms = {"the prior": x0[held], "descended": target[held]}
        if args.run:
            rooms["the adapter"] = x0[held] + adapter_move(held)
        for name, x in rooms.items():
            r = evaluate_layouts(SceneBatch.decode(x.clamp(-1, 1), prior.stats, floors).to_layouts())
            print(f"the held-out rooms, {name}: Col_obj {r['Col_obj']:.1%}, R_reach {r['R_reach']:.1%}")

    fresh = SceneDenoiser(prior.denoiser.config, prior.denoiser.feature_dim)
    fresh.set_metric_scale(prior.stats)

    def fresh_move(rows):
        return predictions(fresh, x0[rows], cond[rows])

    optimizer = torch.optim.Adam(fresh.parameters(), lr=args.lr)
    t0 = torch.zeros(args.batch, dtype=torch.long)
    for epoch in range(1, args.epochs + 1):
        fresh.train()
        for rows in train[torch.randperm(len(train), generator=generator)].split(args.batch):
            w = weight[rows]
            loss = ((fresh(x0[rows], t0[:len(rows)], cond[rows]) - move[rows]).square() * w).sum() / w.sum()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        fresh.eval()
        print(f"epoch {epoch}: the fresh network explains {score(fresh_move, held):.1%} of the held-out rooms' "
              f"move, {score(fresh_move, seen):.1%} of as many trained-on rooms'", flush=True)


if __name__ == "__main__":
    main()
