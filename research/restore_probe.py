"""Does a policy keep the rooms it is handed? Rooms (a layout file, or a ``search_sft.py --cache`` file of searched
rooms) noised to a timestep t of the sampling chain and restored by the policy from there to t = 0 (the config's
steps and eta, the rooms' classes given, as ``search_sft.py`` trains): per t, Col_obj and the task's pass rate of the
restored rooms, and the median distance (m) their ground objects moved; with ``--jitter``, the same figures of the rooms
with random noise of each sigma (m) added to their positions, for a move of the same size with no direction. A prior
pulls rooms off its own manifold back to it at low noise; an adapter that learned a task's rooms keeps them. t = 0 is
the chain's last step alone. With ``--task``, also how many of the rooms passing as handed still pass (and of the others
now pass); with ``--by-class``, per class, how far its objects moved and the pass rate with them put back where they
were handed. ``eval_prior.py --denoise-from`` does the same for a prior and its data's rooms.

    .venv/bin/python research/restore_probe.py experiments/ablations/task_wheelchair_gradient.yaml ROOMS.pt \\
        --task wheelchair [--init RUN] [--t 0 50 100 200 300 500] [--by-class]
    .venv/bin/python research/restore_probe.py experiments/ablations/stage1_livingroom_depth.yaml DESCENDED.json
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from eval_prior import denoise_chain  # noqa: E402
from search_sft import cached_rooms, task_policy  # noqa: E402
from iarcs_env.metrics import evaluate_layouts  # noqa: E402
from iarcs_env.schedule import standard_normal  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402
from iarcs_env.tasks import task_results  # noqa: E402


def load_rooms(path: str, spec, cfg, count: int | None) -> SceneBatch:
    """The first ``count`` rooms of a layout file (centred) or of a ``search_sft.py`` cache file."""
    if str(path).endswith(".pt"):
        rooms = cached_rooms(path, spec, cfg)
        return rooms[:count] if count else rooms
    from iarcs_env.datasets import load_layouts

    layouts = [lay.centred() for lay in load_layouts(path, cfg.room)[:count]]
    return SceneBatch.from_layouts(layouts, spec)


@torch.no_grad()
def restore(policy, rooms: SceneBatch, start: int, num_steps: int, eta: float, seed: int = 0) -> SceneBatch:
    """``rooms`` noised to the chain's first timestep at or below ``start`` and denoised by the policy to t = 0."""
    prior = policy.prior
    x0, classes = rooms.encode(prior.stats), rooms.labels
    first = max(int(t) for t in prior.schedule.set_timesteps(num_steps) if int(t) <= start)
    generator = torch.Generator().manual_seed(seed)
    fn = prior.model_fn(prior.floor_condition(rooms.floors), eps_fn=functools.partial(policy.eps, classes=classes))
    x = prior.schedule.q_sample(x0, torch.full((len(rooms),), first), standard_normal(x0.shape, generator))
    x = denoise_chain(prior, fn, x, first, num_steps, eta, generator, classes)
    return SceneBatch.decode(x, prior.stats, rooms.floors)


def ground_move(before: SceneBatch, after: SceneBatch) -> float:
    """Median floor distance (m) the ground objects moved."""
    move = (after.translations - before.translations)[..., 0:3:2].norm(dim=-1)
    return float(move[before.ground_mask].median())


def jitter(rooms: SceneBatch, sigma: float, generator: torch.Generator) -> SceneBatch:
    """``rooms`` with N(0, sigma^2) (m) added to each object's x and z."""
    noise = torch.randn(rooms.translations.shape, generator=generator, dtype=rooms.translations.dtype) * sigma
    noise[..., 1] = 0
    return SceneBatch(rooms.spec, rooms.labels, rooms.translations + noise, rooms.half_sizes, rooms.yaws, rooms.floors)


def figures(rooms: SceneBatch, task: str | None, handed: SceneBatch | None = None) -> str:
    """Col_obj (and the task's pass rate) of ``rooms``; with the ``handed`` rooms they came from, the share of those
    passing as handed that still pass, and of the others that now pass."""
    text = f"Col_obj {evaluate_layouts(rooms.to_layouts())['Col_obj']:.1%}"
    if not task:
        return text
    passes = task_results(task, rooms)
    text += f", {task} {passes.mean():.1%}"
    if handed is not None:
        before = task_results(task, handed)
        share = [f"{p.mean():.1%}" if len(p) else "–" for p in (passes[before], passes[~before])]
        text += f" (of those passing as handed {share[0]} still pass, of the others {share[1]})"
    return text


def put_back(restored: SceneBatch, handed: SceneBatch, task: str, min_objects: int = 20) -> str:
    """Per class (of ``min_objects`` ground objects or more): the median distance (m) its ground objects moved, and
    the task's pass rate of the restored rooms with that class's objects put back where they were handed (position
    and yaw): which class's drift costs the passes."""
    move = (restored.translations - handed.translations)[..., 0:3:2].norm(dim=-1)
    parts = []
    for c, name in enumerate(handed.spec.classes):
        mask = (handed.labels == c) & handed.ground_mask
        if mask.sum() < min_objects:
            continue
        trans, yaws = restored.translations.clone(), restored.yaws.clone()
        trans[mask], yaws[mask] = handed.translations[mask], handed.yaws[mask]
        fixed = SceneBatch(restored.spec, restored.labels, trans, restored.half_sizes, yaws, restored.floors)
        parts.append(f"{name} {float(move[mask].median()):.2f} m, {task_results(task, fixed).mean():.1%}")
    return "; ".join(parts)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a task training config (its prior, stage-1 adapter, adapted features)")
    parser.add_argument("rooms", help="a layout file (neutral JSON) or a search_sft.py --cache file")
    parser.add_argument("--task", help="a task checker to score the restored rooms with too")
    parser.add_argument("--init", help="a run folder (search_sft.py --out, iarcs train) whose adapter restores")
    parser.add_argument("--rooms", type=int, dest="count", help="only the first N rooms")
    parser.add_argument("--t", type=int, nargs="+", default=[0, 50, 100, 200, 300, 500],
                        help="timesteps to restore from (each the chain's first step at or below it)")
    parser.add_argument("--jitter", type=float, nargs="*", default=[], help="position noise sigmas (m) to compare")
    parser.add_argument("--by-class", action="store_true",
                        help="with --task: per class, how far its objects moved and the pass rate with them put back")
    args = parser.parse_args(argv)
    cfg, policy = task_policy(args.config, args.init)
    rooms = load_rooms(args.rooms, policy.prior.spec, cfg, args.count)
    print(f"{len(rooms)} rooms as handed: {figures(rooms, args.task)}")
    generator = torch.Generator().manual_seed(1)
    for sigma in args.jitter:
        out = jitter(rooms, sigma, generator)
        print(f"jittered by sigma = {sigma} m: {figures(out, args.task)}, ground objects moved "
              f"{ground_move(rooms, out):.3f} m (median)")
    for start in args.t:
        out = restore(policy, rooms, start, cfg.num_steps, cfg.eta)
        print(f"restored from t = {start}: {figures(out, args.task, rooms)}, ground objects moved "
              f"{ground_move(rooms, out):.3f} m (median)", flush=True)
        if args.by_class and args.task:
            print(f"  put back, by class (median move, {args.task}): {put_back(out, rooms, args.task)}", flush=True)


if __name__ == "__main__":
    main()
