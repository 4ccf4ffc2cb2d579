"""Does descent imitation carry over to new rooms with many more rooms than an online run sees? The prior's rooms
on ``--rooms`` training floors (the config's floor seed), each descended once (``agents/descent_imitation.py``'s
targets, the config's penalty), then the adapter trained offline for ``--epochs`` passes over them on the one step
whose prediction is the room sampled (t = 0): x0_hat(x_t) regressed onto the prior's own x0_hat plus the descent's
move. After each pass: how well it fits its rooms (the share of the move's mean square its prediction explains on
them, as ``research/descent_probe.py`` scores it) and how far that carries over (on ``--other-floors`` other floors,
seed 4242, the noise fixed: the penalty and Col_obj of the rooms sampled with the adapter and, first, without it).

    .venv/bin/python research/descent_offline.py experiments/ablations/stage1_livingroom_descent.yaml \
        --rooms 16384 --epochs 10 --cache ROOMS.pt --out RUN [--init RUN --lr 0.003]
    iarcs sample --room livingroom --checkpoint RUN ...

``--cache`` keeps the descended rooms (made once, reused when the file exists; several files: their rooms together,
e.g. from configs of other floor seeds); ``--out`` writes a run folder
that ``iarcs sample --checkpoint`` reads; ``--init`` starts from such a folder's adapter.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch
import yaml
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents import policy as policy_module  # noqa: E402
from agents.denoiser import centre_floor  # noqa: E402
from agents.physics_gradient import adapted_object_weights, penalty_weights, physics_penalty  # noqa: E402
from agents.train import ADAPTERS_DIR, build, load_train_config  # noqa: E402
from iarcs_env.datasets.procedural import generate_layouts  # noqa: E402
from iarcs_env.env import default_floors  # noqa: E402
from iarcs_env.metrics import evaluate_layouts  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402

CHUNK = 128


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a descent-imitation training config (room, prior, penalty, adapter)")
    parser.add_argument("--rooms", type=int, default=8192)
    parser.add_argument("--epochs", type=int, default=8)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--other-floors", type=int, default=64,
                        help="held-out floors sampled after each pass (0: none, e.g. a run that only makes --cache)")
    parser.add_argument("--lr", type=float, help="learning rate (default: the config's)")
    parser.add_argument("--cache", action="append", default=[],
                        help="a file for the descended rooms: written once, then read; given more than once, the "
                             "files' rooms together (each written before by a run of its own)")
    parser.add_argument("--init", help="a run folder (of --out) whose adapter to start from")
    parser.add_argument("--out", help="write a run folder with the trained adapter")
    parser.add_argument("--lora-targets", help="a regular expression of the layers the LoRA adapts (peft's "
                        "target_modules), in place of the attention projections (agents.policy.LORA_TARGETS)")
    args = parser.parse_args(argv)
    cfg = load_train_config(args.config)
    algo, policy = build_with_targets(cfg, args.lora_targets)
    weights = penalty_weights(algo.config, algo.contact())
    generator = torch.Generator().manual_seed(cfg.seed)

    if args.init:
        policy.load_adapter(Path(args.init) / ADAPTERS_DIR / cfg.adapter, cfg.adapter)
    if args.cache and all(Path(c).exists() for c in args.cache):
        x_in, cond, target = load_rooms(args.cache)
    elif len(args.cache) > 1:
        raise SystemExit(f"missing: {', '.join(c for c in args.cache if not Path(c).exists())} (make each file with "
                         f"a run of its own)")
    else:
        x_in, cond, target = descended_rooms(cfg, algo, policy, args.rooms, generator)
        if args.cache:
            torch.save({"x_in": x_in, "cond": cond, "target": target}, args.cache[0])
    weight = adapted_object_weights(policy, target)
    t0 = torch.zeros(len(x_in), dtype=torch.long)

    other = held_out_floors(cfg.room, args.other_floors) if args.other_floors > 0 else []

    def carried_over(who: str) -> str:
        return f"; {len(other)} other floors, {who}: {sampled_on(policy, cfg, other, weights)}" if other else ""

    with policy.base_policy():
        prior_x0 = predictions(policy.predict_x0, x_in, cond).clamp(-1, 1)
        print(f"{len(x_in)} rooms{carried_over('the prior')}")
    optimizer = torch.optim.Adam(policy.trainable_parameters(), lr=args.lr or algo.config.learning_rate)
    policy.model.eval()
    for epoch in range(1, args.epochs + 1):
        losses = []
        for rows in torch.randperm(len(x_in), generator=generator).split(args.batch):
            pred = policy.predict_x0(x_in[rows], t0[rows], cond[rows], straight_through=True)
            w = weight[rows]
            loss = ((pred - target[rows]).square() * w).sum() / w.sum().clamp_min(1)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.trainable_parameters(), algo.config.max_grad_norm)
            optimizer.step()
            losses.append(loss.item())
        fit = explained(predictions(policy.predict_x0, x_in, cond).clamp(-1, 1) - prior_x0, target - prior_x0, weight)
        print(f"epoch {epoch}: loss {sum(losses) / len(losses):.5f}, explains {fit:.0%} of the move on its rooms"
              f"{carried_over('the adapter')}", flush=True)
        if args.out:  # a run folder iarcs sample --checkpoint reads, after every pass
            Path(args.out).mkdir(parents=True, exist_ok=True)
            (Path(args.out) / "config.yaml").write_text(yaml.safe_dump(dataclasses.asdict(cfg), sort_keys=False))
            policy.save_adapter(Path(args.out) / ADAPTERS_DIR)


def explained(pred: torch.Tensor, move: torch.Tensor, weight: torch.Tensor) -> float:
    """1 - the weighted mean square of ``pred - move`` over that of ``move``."""
    return 1.0 - float(((pred - move).square() * weight).sum() / (move.square() * weight).sum())


def predictions(fn, x: torch.Tensor, cond: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """``fn(x, t = 0, cond)`` (a policy's or a network's last-step prediction) over the rooms in chunks, no grad."""
    t0 = torch.zeros(chunk, dtype=torch.long)
    with torch.no_grad():
        return torch.cat([fn(x[i:i + chunk], t0[:len(x[i:i + chunk])], cond[i:i + chunk])
                          for i in range(0, len(x), chunk)])


def build_with_targets(cfg, lora_targets: str | None = None):
    """The config's algorithm and policy, the LoRA on the layers ``lora_targets`` (a regular expression, peft's
    target_modules) matches in place of the attention projections (agents.policy.LORA_TARGETS)."""
    if lora_targets:
        policy_module.LORA_TARGETS = lora_targets
    algo, policy, _ = build(cfg)
    return algo, policy


def load_rooms(paths) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The x_in, cond and target of the cache files ``paths``, their rooms together in the files' order."""
    return tuple(torch.cat(parts) for parts in zip(*(torch.load(p).values() for p in paths)))


def held_out_floors(room: str, count: int) -> list:
    """``count`` procedural floors of seed 4242, which neither pretraining (seed 0) nor RL (1000) sees."""
    return [centre_floor(f) for f in default_floors(room, count=count, seed=4242)]


def sampled_on(policy, cfg, floors, weights: dict) -> str:
    """The penalty (``weights``: :func:`~agents.physics_gradient.penalty_weights`) and Col_obj of the rooms the
    policy samples on ``floors``, the noise fixed (seed 0)."""
    with torch.no_grad():
        x0 = policy.prior.sample_features(floors, cfg.num_steps, cfg.eta, torch.Generator().manual_seed(0),
                                          eps_fn=policy.eps)
    penalty = float(physics_penalty(x0, policy.prior.stats, floors, **weights).mean())
    col = evaluate_layouts(SceneBatch.decode(x0, policy.prior.stats, floors).to_layouts())["Col_obj"]
    return f"penalty {penalty:.3f}, Col_obj {col:.1%}"


def descended_rooms(cfg, algo, policy, count: int, generator: torch.Generator):
    """The prior's rooms on ``count`` training floors: the state x_t of each chain's last step, the floor condition,
    and the target of the last step's prediction (the room, clipped as decoding does, plus the descent's move)."""
    prior = policy.prior
    floors = [lay.centred().floor for lay in generate_layouts(cfg.room, count, seed=cfg.floor_seed)]
    inputs, conds, targets, penalties = [], [], [], []
    start = time.time()
    for i in tqdm(range(0, len(floors), CHUNK), desc="prior rooms, descended"):
        chunk = floors[i:i + CHUNK]
        with torch.no_grad(), policy.base_policy():
            x0, trajectory = prior.sample_features(chunk, cfg.num_steps, cfg.eta, generator, eps_fn=policy.eps,
                                                   return_trajectory=True)
        move, info = algo.targets(x0, chunk)
        inputs.append(trajectory["states"][-2])
        conds.append(prior.floor_condition(chunk))
        targets.append(x0.clamp(-1, 1) + move)
        penalties.append((info["physics"], info["physics_descended"]))
    before = sum(p[0] for p in penalties) / len(penalties)
    after = sum(p[1] for p in penalties) / len(penalties)
    print(f"{len(floors)} rooms in {time.time() - start:.0f} s: penalty {before:.3f}, descended {after:.3f}")
    return torch.cat(inputs), torch.cat(conds), torch.cat(targets)


if __name__ == "__main__":
    main()
