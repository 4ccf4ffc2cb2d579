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
        --rooms 1024 --steps 1500 [--margin 0.1] --cache ROOMS.pt --out RUN
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


FIELDS = ("labels", "translations", "half_sizes", "yaws")


HELD_OUT_SEED = 4242
"""The seed of the held-out floors the fine-tuning scripts measure success on."""


def procedural_floors(room: str, count: int, seed: int) -> list:
    """The centred floors of ``count`` procedural rooms of ``seed``."""
    return [lay.centred().floor for lay in generate_layouts(room, count, seed=seed)]


def cat(batches: list[SceneBatch]) -> SceneBatch:
    """One batch of ``batches``' rooms (float32 geometry)."""
    return SceneBatch(batches[0].spec, *(torch.cat([getattr(b, k) for b in batches]).to(
        torch.long if k == "labels" else torch.float32) for k in FIELDS), [f for b in batches for f in b.floors])


def cached_rooms(path: str, spec, cfg) -> SceneBatch:
    """The searched rooms of a ``--cache`` file, on their floors (regenerated from the seed it records)."""
    fields = torch.load(path)
    floors = procedural_floors(cfg.room, len(fields["labels"]), fields.get("floor_seed", cfg.floor_seed))
    return SceneBatch(spec, *(fields[k] for k in FIELDS), floors)


def searched_rooms(policy, floors, task: str, generator, margin: float = 0.0) -> SceneBatch:
    """The policy's rooms on ``floors``, rearranged by the layout search for ``task`` (scored with ``margin``)."""
    out = []
    for i in tqdm(range(0, len(floors), CHUNK), desc="rooms sampled and searched", unit="chunk"):
        with torch.no_grad():
            batch = policy.sample(floors[i:i + CHUNK], generator)
        out.append(search_rooms(batch, task, margin=margin))
    return cat(out)


def success(policy, floors, task: str) -> float:
    with torch.no_grad():
        return float(task_results(task, policy.sample(floors, torch.Generator().manual_seed(0))).mean())


def denoising_square(policy, x0: torch.Tensor, cond: torch.Tensor, classes: torch.Tensor, weight: torch.Tensor,
                     t: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """The mean square (``weight``ed) of the policy's x0_hat against rooms ``x0`` (model features) noised to timesteps
    ``t``, their ``classes`` given: the denoising loss of a fine-tuning onto them."""
    prior = policy.prior
    noise = torch.randn(x0.shape, generator=generator)
    x_t = prior.with_classes(prior.schedule.q_sample(x0, t, noise), t, classes, generator)
    pred = policy.predict_x0(x_t, t, cond, classes, straight_through=True)
    return ((pred - x0).square() * weight).sum() / weight.sum().clamp_min(1)


def fine_tune(policy, rooms: SceneBatch, params: list, steps: int, lr: float, generator: torch.Generator,
              every: int, report, batch: int = 64, t_range: tuple[int, int] | None = None) -> None:
    """``steps`` steps of ``batch`` of ``rooms``, each noised to a uniform timestep (in ``t_range`` = [lo, hi) when
    given), the policy's x0_hat regressed onto the room (its adapted features), training ``params`` with Adam;
    ``report(step, mean loss)`` every ``every`` steps and at the last."""
    prior = policy.prior
    lo, hi = t_range or (0, prior.schedule.num_train_timesteps)
    x0, cond, classes = rooms.encode(prior.stats), prior.floor_condition(rooms.floors), rooms.labels
    weight = adapted_object_weights(policy, x0)
    optimizer = torch.optim.Adam(params, lr=lr)
    policy.model.eval()
    losses = []
    for step in tqdm(range(1, steps + 1), desc="fine-tuning on the rooms", unit="step"):
        rows = torch.randint(0, len(x0), (batch,), generator=generator)
        t = torch.randint(lo, hi, (batch,), generator=generator)
        loss = denoising_square(policy, x0[rows], cond[rows], classes[rows], weight[rows], t, generator)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        losses.append(loss.item())
        if step % every == 0 or step == steps:
            report(step, sum(losses) / len(losses))
            losses = []


def held_out_report(policy, cfg, task: str, other: list, out: str | None = None):
    """A ``report`` for :func:`fine_tune`: the loss and the task's success on the ``other`` floors, and with ``out`` the
    run folder written (:func:`save_run`) and both figures in its ``tb/``, whose span from this call to the last
    report is the run's training time (what ``experiments/ship_task_adapter.py`` charges)."""
    writer = None
    if out:
        from torch.utils.tensorboard import SummaryWriter
        writer = SummaryWriter(str(Path(out) / "tb"))

    def report(step: int, loss: float) -> None:
        rate = success(policy, other, task)
        tqdm.write(f"step {step}: loss {loss:.4f}; {task} on {len(other)} other floors {rate:.1%}")
        if out:
            save_run(policy, cfg, out)
            writer.add_scalar("fine_tune/loss", loss, step)
            writer.add_scalar(f"fine_tune/{task}_held_out", rate, step)
            writer.flush()
    return report


def save_run(policy, cfg, out: str) -> None:
    """A run folder ``iarcs sample --checkpoint`` reads: the config and the adapter."""
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / "config.yaml").write_text(yaml.safe_dump(dataclasses.asdict(cfg), sort_keys=False))
    policy.save_adapter(Path(out) / ADAPTERS_DIR)


def task_policy(config: str, init: str | None = None, lora_targets: str | None = None):
    """(config, policy) of a task training config on one torch thread, the adapter of the run folder ``init`` loaded
    when given (``lora_targets``: as :func:`descent_offline.build_with_targets`)."""
    torch.set_num_threads(1)
    cfg = load_train_config(config)
    _, policy = build_with_targets(cfg, lora_targets)
    if init:
        policy.load_adapter(Path(init) / ADAPTERS_DIR / cfg.adapter, cfg.adapter)
    return cfg, policy


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
    parser.add_argument("--cache", action="append", default=[],
                        help="a file for the searched rooms: written once, then read; given more than once, the files' "
                             "rooms together (each written before by a run of its own)")
    parser.add_argument("--floor-seed", type=int, help="the training floors' seed (default: the config's)")
    parser.add_argument("--margin", type=float, default=0.0,
                        help="search for rooms that pass with a wheelchair and turning disk this much (m) wider")
    parser.add_argument("--out", help="write a run folder with the trained adapter")
    parser.add_argument("--init", help="a run folder (of --out) whose adapter to start from")
    parser.add_argument("--lora-targets", help="a regular expression of the layers the LoRA adapts, in place of the "
                        "attention projections (as research/descent_offline.py's)")
    args = parser.parse_args(argv)
    cfg, policy = task_policy(args.config, args.init, args.lora_targets)
    prior, generator = policy.prior, torch.Generator().manual_seed(cfg.seed)
    other = procedural_floors(cfg.room, args.other_floors, HELD_OUT_SEED)
    report = held_out_report(policy, cfg, args.task, other, args.out)  # before the search: its time counts too
    if args.cache and all(Path(c).exists() for c in args.cache):
        rooms = cat([cached_rooms(c, prior.spec, cfg) for c in args.cache])
    elif len(args.cache) > 1:
        raise SystemExit(f"missing: {', '.join(c for c in args.cache if not Path(c).exists())} (make each file with "
                         "a run of its own)")
    else:
        seed = cfg.floor_seed if args.floor_seed is None else args.floor_seed
        rooms = searched_rooms(policy, procedural_floors(cfg.room, args.rooms, seed), args.task, generator, args.margin)
        if args.cache:
            torch.save({"floor_seed": seed, **{k: getattr(rooms, k) for k in FIELDS}}, args.cache[0])
    floors = rooms.floors
    print(f"{len(rooms)} searched rooms: {args.task} {task_results(args.task, rooms).mean():.1%}")
    own = floors[:args.other_floors]
    print(f"step 0: {args.task} on {len(other)} other floors {success(policy, other, args.task):.1%}, on the first "
          f"{len(own)} of its training floors {success(policy, own, args.task):.1%}", flush=True)
    fine_tune(policy, rooms, policy.trainable_parameters(), args.steps, args.lr, generator, args.eval_every, report,
              args.batch)


if __name__ == "__main__":
    main()
