"""Scene-prior sampling throughput: scenes per second of a 20-step DDIM rollout (eta = 1) at batch 32 and
256, for the ``small`` and ``paper`` presets, next to the float32 matmul rate measured in the same run
times the model's FLOPs per scene (the compute-bound limit), as a fraction of that limit.

Run it as a script (``python benchmarks/bench_sampling.py [--json out.json] [--quick] [--device cuda]``); never
``import benchmarks`` (torchrl installs a site-packages package of that name). Weights are random: the
speed of a network does not depend on its values.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from agents.denoiser import DenoiserConfig, SceneDenoiser, ScenePrior  # noqa: E402
from iarcs_env import FloorPlan, get_room  # noqa: E402
from iarcs_env.stats import DatasetStats  # noqa: E402


def synchronize(device: torch.device) -> None:
    """Wait for the GPU's queued work (timings of asynchronous CUDA calls would stop too early)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def matmul_flops(device: torch.device, n: int = 1024, seconds: float = 2.0) -> float:
    """Measured float32 matmul rate (FLOP/s) on square n x n matrices on ``device`` (4096 on a GPU)."""
    n = 4096 if device.type == "cuda" else n
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    for _ in range(3):
        a @ b
    synchronize(device)
    reps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        reps += 1
    synchronize(device)
    return 2 * n**3 * reps / (time.perf_counter() - t0)


def floors(batch: int) -> list[FloorPlan]:
    shapes = [[(0, 0), (4, 0), (4, 3), (0, 3)], [(0, 0), (4, 0), (4, 2), (2, 2), (2, 4), (0, 4)],
              [(0, 0), (3.2, 0), (3.2, 3.6), (0, 3.6)]]
    return [FloorPlan.from_vertices(shapes[i % 3]) for i in range(batch)]


def bench(preset: str, batch: int, steps: int, repeats: int, device: torch.device, room: str = "bedroom") -> dict:
    spec = get_room(room)
    stats = DatasetStats(spec.name, [-3, 0, -3, 3, 2.6, 3], [0.05, 0.05, 0.05, 1.5, 1.3, 1.5])
    torch.manual_seed(0)
    cfg = DenoiserConfig.from_preset(preset)
    prior = ScenePrior(SceneDenoiser(cfg, spec.feature_dim).eval(), stats)
    with torch.no_grad():
        for p in prior.denoiser.parameters():
            p.normal_(0, 0.02)
    prior.to(device)
    fl = floors(batch)
    prior.sample(fl[: min(batch, 8)], num_steps=2)  # warm-up
    times = []
    for r in range(repeats):
        g = torch.Generator().manual_seed(r)
        t0 = time.perf_counter()
        prior.sample(fl, num_steps=steps, eta=1.0, generator=g)
        synchronize(device)
        times.append(time.perf_counter() - t0)
    best = min(times)
    net = prior.denoiser
    flops = steps * net.flops_per_scene(spec.max_objects) + net.flops_per_scene(spec.max_objects, include_floor=True) \
        - net.flops_per_scene(spec.max_objects)
    return {"preset": preset, "room": spec.name, "batch": batch, "ddim_steps": steps, "seconds_best": best,
            "seconds_all": times, "scenes_per_s": batch / best, "parameters": net.num_parameters(),
            "flops_per_scene": flops}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", default=None, help="also write the results to this JSON file")
    ap.add_argument("--quick", action="store_true", help="small preset at batch 32 only")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N: where the model and the "
                                                    "matmul reference run")
    args = ap.parse_args(argv)

    from agents.config import resolve_device

    try:
        device = resolve_device(args.device)
    except ValueError as err:
        ap.error(str(err))
    rate = matmul_flops(device)
    rows = []
    plan = [("small", 32)] if args.quick else [("small", 32), ("small", 256), ("paper", 32), ("paper", 256)]
    for preset, batch in plan:
        repeats = 3 if preset == "small" else (2 if batch <= 32 else 1)
        row = bench(preset, batch, args.steps, repeats, device)
        row["limit_scenes_per_s"] = rate / row["flops_per_scene"]
        row["fraction_of_limit"] = row["scenes_per_s"] / row["limit_scenes_per_s"]
        rows.append(row)
    where = (torch.cuda.get_device_name(device) if device.type == "cuda" else
             f"{torch.get_num_threads()} threads, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs")
    print(f"torch {torch.__version__}, {where}; float32 matmul {rate / 1e9:.1f} GFLOP/s")
    print(f"{'preset':<7}{'batch':>6}{'params':>11}{'MFLOP/scene':>13}{'rollout s':>11}{'scenes/s':>10}"
          f"{'limit/s':>10}{'of limit':>10}")
    for r in rows:
        print(f"{r['preset']:<7}{r['batch']:>6}{r['parameters']:>11,}{r['flops_per_scene'] / 1e6:>13.1f}"
              f"{r['seconds_best']:>11.3f}{r['scenes_per_s']:>10.1f}{r['limit_scenes_per_s']:>10.1f}"
              f"{r['fraction_of_limit']:>10.1%}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"matmul_flops": rate, "torch": torch.__version__, "device": str(device),
                                               "threads": torch.get_num_threads(), "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
