"""Quality of a scene prior against its training data and against real rooms, sampled on the same floors.

Run as a script::

    .venv/bin/python research/eval_prior.py --checkpoint agents/checkpoints/bedroom_small.pt \
        --reference procedural --data-seed 0 --num-scenes 500 --json out/eval/prior_train.json
    .venv/bin/python research/eval_prior.py --reference ../shared/data/3dfront/bedroom_val.json

For each reference room the prior samples one scene on that room's floor plan (20-step DDIM), so the
reference and generated sets share their floors. Reported, for the reference and for the samples:
``iarcs_env.metrics.evaluate_layouts`` (Col_obj, Col_scene, R_out, R_off_floor, R_reach, R_walkable, objects per room,
KL_class = KL(reference || generated) with eps 1e-6, count_distance = earth mover's distance of the
object counts), plus ``iarcs_env.datasets.realism``'s object-count TVD and class KL (eps 1e-3).
``--reference procedural`` uses the embedded generator with ``--data-seed`` (0 = the first rooms of the
prior's training data; another seed = held-out rooms). ``--floor-usage`` also measures how much the prior
uses its floor condition: the epsilon loss on the reference rooms with their own floors, with every room
given the next room's floor, and with the all-zero (unconditional) floor (the same t and noise), and
R_out of the samples checked against their own floors and against the next room's, and the epsilon MSE of the
translation x, z features alone at t = 10, 50, 100, 300 with each of the three floors. ``--denoise-from``
measures where the placement error arises: the reference rooms are noised to x_t (t on the 20-step DDIM
grid, e.g. 50 200 950) and denoised by the prior for the rest of the rollout; the metrics of the result
say whether the prior can restore a real layout from that noise level, and the median distance between
each restored object and its original says how precisely (from t = 50 the rollout is one step: x0_hat).
``--collision-pairs`` lists which class pairs collide (and the overlap volumes) in the reference and in
the samples of the first eta: it tells collisions the data has too (a nightstand tucked against a bed)
from gross placement errors.
``--tasks`` adds the five paper tasks' checker success rates to every row (with ``--denoise-from``: at which
noise level the relations the tasks test are lost). Nothing is written into the repository unless
``--json`` / ``--markdown`` point there; real rooms are only read.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from agents.denoiser import ScenePrior  # noqa: E402
from iarcs_env.datasets import load_layouts  # noqa: E402
from iarcs_env.datasets.realism import class_kl as realism_class_kl  # noqa: E402
from iarcs_env.datasets.realism import count_tvd  # noqa: E402
from iarcs_env.geometry import COLLISION_VOLUME, box_overlap_volumes  # noqa: E402
from iarcs_env import relations as rel  # noqa: E402
from iarcs_env.metrics import evaluate_layouts  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402
from iarcs_env.tasks import TASKS, task_success  # noqa: E402

KEYS = ("Col_obj", "Col_scene", "R_out", "R_off_floor", "R_reach", "R_walkable", "mean_objects")


def evaluate(prior: ScenePrior, reference: list, seed: int = 0, etas=(1.0,), num_steps: int = 20,
             batch_size: int = 64, guidance_scale: float = 1.0) -> dict:
    floors = [lay.centred().floor for lay in reference]
    rows = {"reference": evaluate_layouts(reference)}
    gens = {}
    for eta in etas:
        t0 = time.perf_counter()
        gen = prior.sample(floors, num_steps=num_steps, eta=eta, generator=torch.Generator().manual_seed(seed),
                           batch_size=batch_size, guidance_scale=guidance_scale).to_layouts()
        seconds = time.perf_counter() - t0
        r = evaluate_layouts(gen, reference=reference)
        r["count_tvd"] = count_tvd(reference, gen)
        r["class_kl_realism"] = realism_class_kl(reference, gen)
        r["sample_seconds"] = seconds
        rows[f"prior, eta = {eta:g}"] = r
        gens[eta] = gen
    evaluate.last_generated = gens
    return rows


@torch.no_grad()
def floor_usage(prior: ScenePrior, reference: list, gen: list | None = None) -> dict:
    """Epsilon loss with own / next room's / zero floors, and R_out of ``gen`` on own / next floors."""
    import copy

    from agents.pretrain_data import SceneTensors, encode_batch

    net = prior.denoiser.eval()
    data = SceneTensors.from_layouts(reference, prior.num_slots)
    x0, floor = encode_batch(prior.spec, prior.stats, *data.batch(torch.arange(len(data))))
    out = {}
    conditions = {"own_floor": floor, "next_floor": floor.roll(1, 0), "zero_floor": torch.zeros_like(floor)}
    for name, fl in conditions.items():
        g = torch.Generator().manual_seed(1234)
        out[f"loss_{name}"] = float(prior.schedule.training_loss(lambda x, t: net(x, t, fl), x0, g))
    # the translation x, z part of the loss at fixed small t, where objects get placed against the walls
    for t in (10, 50, 100, 300):
        noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(t))
        tt = torch.full((x0.shape[0],), t)
        x_t = prior.schedule.q_sample(x0, tt, noise)
        for name, fl in conditions.items():
            out[f"xz_loss_t{t}_{name}"] = float((net(x_t, tt, fl) - noise)[..., 0:3:2].pow(2).mean())
    if gen is not None:
        floors = [lay.centred().floor for lay in reference]
        swapped = []
        for i, lay in enumerate(gen):
            lay = copy.copy(lay)
            lay.floor = floors[(i + 1) % len(floors)]
            swapped.append(lay)
        out["R_out_own_floor"] = evaluate_layouts(gen)["R_out"]
        out["R_out_next_floor"] = evaluate_layouts(swapped)["R_out"]
    return out


@torch.no_grad()
def denoise_chain(prior: ScenePrior, fn, x: torch.Tensor, start: int, num_steps: int, eta: float,
                  generator: torch.Generator, classes: torch.Tensor | None = None) -> torch.Tensor:
    """x_t at ``start`` (a step of the ``num_steps`` DDIM grid) denoised to t = 0 by ``fn(x_t, t)`` (a
    :meth:`ScenePrior.model_fn`); ``classes`` (B, N): given at every step (:meth:`ScenePrior.with_classes`) and in
    the result."""
    grid = prior.schedule.set_timesteps(num_steps).tolist()
    for t in grid[grid.index(start):]:
        tt = torch.full((x.shape[0],), t)
        x_in = x if classes is None else prior.with_classes(x, tt, classes, generator)
        x = prior.schedule.step(fn(x_in, tt), tt, x, eta=eta, generator=generator).prev_sample
    return x if classes is None else prior.with_clean_classes(x, classes)


@torch.no_grad()
def denoise_from(prior: ScenePrior, reference: list, starts, seed: int = 0, num_steps: int = 20,
                 tasks: bool = False) -> dict:
    """Metrics of the reference rooms noised to each t in ``starts`` and denoised by the prior (DDIM, eta 1),
    with the position errors of the noised and of the denoised objects (and the tasks' success rates)."""
    from agents.pretrain_data import SceneTensors, encode_batch

    data = SceneTensors.from_layouts(reference, prior.num_slots)
    x0, floor = encode_batch(prior.spec, prior.stats, *data.batch(torch.arange(len(data))))
    floors = [lay.centred().floor for lay in reference]
    original = SceneBatch.decode(x0, prior.stats, floors)
    schedule, fn = prior.schedule, prior.model_fn(floor.to(prior.device))
    grid = schedule.set_timesteps(num_steps).tolist()
    out = {}
    for start in starts:
        if start not in grid:
            raise SystemExit(f"--denoise-from {start}: not on the {num_steps}-step DDIM grid {grid}")
        g = torch.Generator().manual_seed(seed)
        x = schedule.q_sample(x0, start, torch.randn(x0.shape, generator=g))
        noised = SceneBatch.decode(x / schedule.alphas_cumprod[start].sqrt(), prior.stats, floors)
        result = SceneBatch.decode(denoise_chain(prior, fn, x, start, num_steps, 1.0, g), prior.stats, floors)
        layouts = result.to_layouts()
        row = out[f"from t = {start}"] = evaluate_layouts(layouts)
        row["position_error_m"] = position_errors(result, original)
        row["position_error_noised_m"] = position_errors(noised, original)
        if tasks:
            add_task_success(row, layouts)
    return out


def add_task_success(row: dict, layouts: list) -> None:
    """``row["tasks"]``: checker success rate of each paper task on ``layouts``."""
    row["tasks"] = {name: task_success(name, layouts) for name in TASKS}


def task_table(rows: dict) -> str:
    lines = ["| scenes | " + " | ".join(TASKS) + " |", "|---|" + "---:|" * len(TASKS)]
    lines += [f"| {name} | " + " | ".join(f"{100 * r['tasks'][t]:.1f}" for t in TASKS) + " |"
              for name, r in rows.items() if "tasks" in r]
    return "\n".join(lines)


def position_errors(result: SceneBatch, reference: SceneBatch) -> dict:
    """Median distance (m) on the floor between each object of ``reference`` and the same slot of ``result``
    (objects whose class the denoising kept): all of them, beds and nightstands."""
    kept = reference.mask & result.mask & (result.labels == reference.labels)
    err = (result.translations[..., 0:3:2] - reference.translations[..., 0:3:2]).norm(dim=-1)
    groups = {"all": kept, "bed": kept & rel.class_mask(reference.labels, reference.spec.classes, ["bed"]),
              "nightstand": kept & rel.class_mask(reference.labels, reference.spec.classes, ["nightstand"])}
    return {name: float(err[m].median()) if m.any() else float("nan") for name, m in groups.items()}


def table(rows: dict) -> str:
    head = ("| scenes | Col_obj | Col_scene | R_out | R_off_floor | R_reach | R_walkable | objects / room "
            "| KL_class (1e-6) | class KL (1e-3) | count TVD | count EMD |\n|---|" + "---:|" * 11)
    lines = [head]
    for name, r in rows.items():
        vals = [f"{r[k]:.3f}" if k != "mean_objects" else f"{r[k]:.2f}" for k in KEYS]
        extra = ([f"{r['KL_class']:.3f}", f"{r['class_kl_realism']:.3f}", f"{r['count_tvd']:.3f}",
                  f"{r['count_distance']:.3f}"] if "KL_class" in r else ["-"] * 4)
        lines.append(f"| {name} | " + " | ".join(vals + extra) + " |")
    return "\n".join(lines)


def collision_pairs(layouts: list) -> dict:
    """The class pairs of colliding ground objects (the Col_obj test) with their counts, most frequent
    first, and the quartiles of their overlap volumes (m^3)."""
    b = SceneBatch.from_layouts(layouts)
    overlap = box_overlap_volumes(b.translations, b.half_sizes, b.yaws, b.ground_mask)
    pairs, volumes = collections.Counter(), []
    for s, i, j in zip(*torch.where(torch.triu(overlap > COLLISION_VOLUME, 1))):
        pairs[" - ".join(sorted(b.spec.classes[b.labels[s, k]] for k in (i, j)))] += 1
        volumes.append(float(overlap[s, i, j]))
    return {"pairs": sum(pairs.values()), "overlap_m3_quartiles": np.quantile(volumes, [0.25, 0.5, 0.75]).tolist()
            if volumes else [], "counts": dict(pairs.most_common())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", default=str(ScenePrior.default_path("bedroom")))
    p.add_argument("--room", default="bedroom")
    p.add_argument("--reference", default="procedural", help="procedural, or a neutral-JSON / ATISS dataset")
    p.add_argument("--data-seed", type=int, default=0, help="procedural generator seed (0: training data)")
    p.add_argument("--num-scenes", type=int, default=500, help="reference rooms (0: all of a file)")
    p.add_argument("--max-objects", type=int, default=0, help="drop reference rooms with more objects (0: keep)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed")
    p.add_argument("--eta", type=float, nargs="+", default=[1.0])
    p.add_argument("--steps", type=int, default=20, help="DDIM steps per sample")
    p.add_argument("--guidance", type=float, default=1.0,
                   help="classifier-free guidance scale on the floor condition (1: none)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--floor-usage", action="store_true", help="also measure how much the floor is used")
    p.add_argument("--denoise-from", type=int, nargs="*", default=[],
                   help="also denoise the reference rooms from these noise levels t (DDIM grid), e.g. 50 200 950")
    p.add_argument("--collision-pairs", action="store_true", help="also list the colliding class pairs")
    p.add_argument("--tasks", action="store_true", help="also report the five paper tasks' success rates")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    prior = ScenePrior.load(args.checkpoint)
    ref = load_layouts(args.reference, args.room, num_scenes=args.num_scenes, seed=args.data_seed)
    if args.max_objects:
        ref = [lay for lay in ref if len(lay) <= args.max_objects]
    if args.num_scenes:
        ref = ref[:args.num_scenes]
    rows = evaluate(prior, ref, seed=args.seed, etas=args.eta, num_steps=args.steps, guidance_scale=args.guidance)
    print(f"{args.checkpoint} (step {prior.meta.get('step')}) vs {args.reference} "
          f"(seed {args.data_seed}, {len(ref)} rooms)")
    print(table(rows))
    if args.tasks:
        add_task_success(rows["reference"], ref)
        for eta, gen in evaluate.last_generated.items():
            add_task_success(rows[f"prior, eta = {eta:g}"], gen)
        print("task success %:")
        print(task_table(rows))
    if args.floor_usage:
        gen = evaluate.last_generated[args.eta[0]]
        rows["floor_usage"] = floor_usage(prior, [lay for lay in ref if len(lay) <= prior.num_slots],
                                          gen if all(len(lay) <= prior.num_slots for lay in ref) else None)
        print("floor usage:", {k: round(v, 4) for k, v in rows["floor_usage"].items()})
    if args.denoise_from:
        rows["denoised_reference"] = denoise_from(prior, [lay for lay in ref if len(lay) <= prior.num_slots],
                                                  args.denoise_from, args.seed, args.steps, args.tasks)
        print("reference rooms noised to t and denoised by the prior:")
        print(table(rows["denoised_reference"]))
        print("median position error (m) against the reference rooms, all objects / beds / nightstands, "
              "noised (x_t / sqrt(alpha_bar_t)) -> denoised:")
        for k, r in rows["denoised_reference"].items():
            a, b = r["position_error_noised_m"], r["position_error_m"]
            print(f"  {k}: " + " / ".join(f"{a[n]:.3f} -> {b[n]:.3f}" for n in ("all", "bed", "nightstand")))
        if args.tasks:
            print(task_table(rows["denoised_reference"]))
    if args.collision_pairs:
        rows["collision_pairs"] = {"reference": collision_pairs(ref),
                                   "prior": collision_pairs(evaluate.last_generated[args.eta[0]])}
        for name, res in rows["collision_pairs"].items():
            print(f"{name}: {res['pairs']} colliding pairs, overlap volume quartiles (m^3) "
                  f"{[round(v, 3) for v in res['overlap_m3_quartiles']]}; " +
                  ", ".join(f"{k} {n}" for k, n in list(res["counts"].items())[:8]) + " (all: --json)")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"args": vars(args), "step": prior.meta.get("step"), "rows": rows},
                                              indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
