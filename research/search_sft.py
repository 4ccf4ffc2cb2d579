"""Can an adapter learn the searched rooms? A task config's adapter (stage 1's, the config's required classes given)
fine-tuned offline with the denoising loss on rooms the greedy layout search rearranged (``layout_search.py``): the
adapter's rooms on ``--rooms`` training floors (the config's floor seed), searched once (``--cache``), then
``--steps`` steps of ``--batch`` rooms, each noised to a uniform timestep, x0_hat regressed onto the searched room
(its adapted features): supervised fine-tuning with the search as the expert, where ``ddpo.layout_search`` (commit
2e040aa, not kept) regressed the policy's own noisy states. At the start and every ``--eval-every`` steps: the
task's success on ``--other-floors`` held-out floors (seed 4242), at the start also on as many of its own training
floors (``--init RUN --steps 0`` only measures RUN's adapter). Writes a run folder that ``iarcs sample
--checkpoint`` reads.

    .venv/bin/python research/search_sft.py experiments/ablations/task_wheelchair_gradient.yaml --task wheelchair \\
        --rooms 1024 --steps 1500 --cache ROOMS.pt --out RUN
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch
import yaml
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from layout_search import search_rooms  # noqa: E402
from agents.physics_gradient import adapted_object_weights  # noqa: E402
from agents.train import ADAPTERS_DIR, load_train_config  # noqa: E402
from descent_offline import build_with_targets  # noqa: E402
from iarcs_env.datasets.procedural import generate_layouts  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402

CHUNK = 64


def searched_rooms(policy, floors, task: str, generator) -> SceneBatch:
    """The policy's rooms on ``floors``, rearranged by the layout search for ``task``."""
    out = []
    for i in tqdm(range(0, len(floors), CHUNK), desc="rooms sampled and searched", unit="chunk"):
        with torch.no_grad():
            batch = policy.sample(floors[i:i + CHUNK], generator)
        out.append(search_rooms(batch, task))
    return SceneBatch(out[0].spec, torch.cat([b.labels for b in out]), torch.cat([b.translations for b in out]).float(),
                      torch.cat([b.half_sizes for b in out]).float(), torch.cat([b.yaws for b in out]).float(),
                      [f for b in out for f in b.floors])


def success(policy, floors, task: str) -> float:
    with torch.no_grad():
        return float(task_results(task, policy.sample(floors, torch.Generator().manual_seed(0))).mean())


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a task training config (room, prior, init_adapter, adapt, required_objects)")
    parser.add_argument("--task", required=True, help="a task with a layout search (layout_search.SCORES)")
    parser.add_argument("--rooms", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--eval-every", type=int, default=250)
    parser.add_argument("--other-floors", type=int, default=64)
    parser.add_argument("--cache", help="a file for the searched rooms: written once, then read")
    parser.add_argument("--out", help="write a run folder with the trained adapter")
    parser.add_argument("--init", help="a run folder (of --out) whose adapter to start from")
    parser.add_argument("--lora-targets", help="a regular expression of the layers the LoRA adapts, in place of the "
                        "attention projections (as research/descent_offline.py's)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg = load_train_config(args.config)
    _, policy = build_with_targets(cfg, args.lora_targets)
    if args.init:
        policy.load_adapter(Path(args.init) / ADAPTERS_DIR / cfg.adapter, cfg.adapter)
    prior, generator = policy.prior, torch.Generator().manual_seed(cfg.seed)
    floors = [lay.centred().floor for lay in generate_layouts(cfg.room, args.rooms, seed=cfg.floor_seed)]
    if args.cache and Path(args.cache).exists():
        fields = torch.load(args.cache)
        rooms = SceneBatch(prior.spec, fields["labels"], fields["translations"], fields["half_sizes"], fields["yaws"],
                           floors)
    else:
        rooms = searched_rooms(policy, floors, args.task, generator)
        if args.cache:
            torch.save({k: getattr(rooms, k) for k in ("labels", "translations", "half_sizes", "yaws")}, args.cache)
    print(f"{len(rooms)} searched rooms: {args.task} {task_results(args.task, rooms).mean():.1%}")
    x0, cond, classes = rooms.encode(prior.stats), prior.floor_condition(floors), rooms.labels
    weight = adapted_object_weights(policy, x0)
    other = [lay.centred().floor for lay in generate_layouts(cfg.room, args.other_floors, seed=4242)]
    own = floors[:args.other_floors]
    print(f"step 0: {args.task} on {len(other)} other floors {success(policy, other, args.task):.1%}, on the first "
          f"{len(own)} of its training floors {success(policy, own, args.task):.1%}", flush=True)
    optimizer = torch.optim.Adam(policy.trainable_parameters(), lr=args.lr)
    schedule = policy.schedule
    policy.model.eval()
    losses = []
    for step in tqdm(range(1, args.steps + 1), desc="fine-tuning on the searched rooms", unit="step"):
        rows = torch.randint(0, len(x0), (args.batch,), generator=generator)
        t = torch.randint(0, schedule.num_train_timesteps, (args.batch,), generator=generator)
        noise = torch.randn(x0[rows].shape, generator=generator)
        x_t = prior.with_classes(schedule.q_sample(x0[rows], t, noise), t, classes[rows], generator)
        pred = policy.predict_x0(x_t, t, cond[rows], classes[rows], straight_through=True)
        w = weight[rows]
        loss = ((pred - x0[rows]).square() * w).sum() / w.sum().clamp_min(1)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.trainable_parameters(), 1.0)
        optimizer.step()
        losses.append(loss.item())
        if step % args.eval_every == 0 or step == args.steps:
            tqdm.write(f"step {step}: loss {sum(losses) / len(losses):.4f}; {args.task} on {len(other)} other floors "
                       f"{success(policy, other, args.task):.1%}")
            losses = []
            if args.out:  # a run folder iarcs sample --checkpoint reads
                Path(args.out).mkdir(parents=True, exist_ok=True)
                (Path(args.out) / "config.yaml").write_text(yaml.safe_dump(dataclasses.asdict(cfg), sort_keys=False))
                policy.save_adapter(Path(args.out) / ADAPTERS_DIR)


if __name__ == "__main__":
    main()
