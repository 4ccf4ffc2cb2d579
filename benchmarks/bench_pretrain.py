"""Pretraining throughput: rooms per second of the full training step (batch drawn and augmented on the
device, forward, backward, optimizer, EMA, the x0-hat losses) with the shipped GPU recipe's losses
(experiments/pretrain_bedroom_gpu.yaml), next to the matrix-multiply rate measured in the same run (square 1024 /
8192 matrices on the CPU / CUDA, in the row's precision; the best of the rates measured before the first row and
after each row's timings, since a shared machine's rate drifts) and the model FLOPs per room:

    fraction = rooms/s x model FLOPs per room / matmul FLOP/s in the row's precision

Rows come in float32 and bfloat16 (autocast) on the CPU, bfloat16 on CUDA (``--precisions``). A bfloat16 row on
the CPU also gives ``fraction_of_fp32_matmul``, against the float32 rate (the issue's reference on a CPU).

Model FLOPs are what torch's FLOP counter counts for one step of the plain layers (the PointNet's
(B, P, F) activation formed, as :meth:`PointNetEncoder.encode_reference` does), forward and backward. The
step as it runs does fewer (its max-pool backward touches only the arg-max points); that count is
``executed_flops_per_room``. Shares: the parts of the step timed with a synchronisation between them (the
x0-hat losses, inside forward and backward, timed on their own). ``plain_rooms_per_s``: the same step with the
plain layers and the x0-hat losses on every scene, as it was before it was made fast, measured in the same run.

    .venv/bin/python benchmarks/bench_pretrain.py [--device cpu|cuda] [--json FILE]
    .venv/bin/python benchmarks/bench_pretrain.py --presets small --batches 512     # one row

``--batches`` takes numbers and ``max``: the largest power of two whose step fits in memory (on a GPU) or
runs in under ``--max-step-seconds`` (on the CPU). Never ``import benchmarks`` (torchrl installs a
site-packages package of that name). Weights are random; the speed does not depend on their values.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from unittest import mock

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

from agents.denoiser import Attention, SceneDenoiser  # noqa: E402
from agents.pointnet import PointNetEncoder  # noqa: E402
from agents.pretrain import (TrainingBatch, batch_loss, draw_batch, load_config, loss_feature_weights,  # noqa: E402
                             training_step)
from agents.x0_losses import out_of_bound_excess, overlap_excess  # noqa: E402
from agents.pretrain_data import SceneTensors, stats_for_training  # noqa: E402
from iarcs_env import get_room  # noqa: E402
from iarcs_env.datasets.procedural import generate_layouts  # noqa: E402
from iarcs_env.schedule import NoiseSchedule  # noqa: E402

RECIPE = "experiments/pretrain_bedroom_gpu.yaml"
PARTS = ("data", "forward", "backward", "optimizer", "ema")


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def matmul_flops(device: torch.device, precision: str, seconds: float = 2.0) -> float:
    """Measured matrix-multiply rate (FLOP/s) in ``precision`` (fp32 or bf16): 1024 x 1024 on the CPU, 8192 x 8192
    on CUDA."""
    n, dtype = 8192 if device.type == "cuda" else 1024, {"fp32": torch.float32, "bf16": torch.bfloat16}[precision]
    a, b = torch.randn(n, n, device=device, dtype=dtype), torch.randn(n, n, device=device, dtype=dtype)
    for _ in range(3):
        a @ b
    synchronize(device)
    reps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        reps += 1
    synchronize(device)
    return 2 * n ** 3 * reps / (time.perf_counter() - t0)


class Setup:
    """A training step of ``preset`` at ``batch`` rooms on ``device``: the shipped GPU recipe's losses, bf16 on
    CUDA, procedural bedrooms resident on the device."""

    def __init__(self, preset: str, batch: int, device: torch.device, data: SceneTensors, stats, compile_: bool,
                 precision: str = "fp32"):
        self.cfg = load_config(RECIPE, preset=preset, batch_size=batch, precision=precision)
        self.spec = get_room(self.cfg.room)
        self.stats, self.batch, self.device = stats, batch, device
        self.data = data.to(device)
        torch.manual_seed(0)
        self.net = SceneDenoiser(self.cfg.denoiser_config(), self.spec.feature_dim).to(device)
        self.net.set_metric_scale(stats)
        self.ema = copy.deepcopy(self.net).requires_grad_(False)
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=1e-4, fused=True)
        self.weights = loss_feature_weights(self.cfg, self.spec.feature_dim)
        self.weights = self.weights.to(device) if self.weights is not None else None
        self.schedule = NoiseSchedule()
        self.gen = torch.Generator(device).manual_seed(0)
        self.model = torch.compile(self.net) if compile_ else self.net

    def next_batch(self) -> TrainingBatch:
        return draw_batch(self.data, self.cfg, self.spec, self.stats, self.gen, self.batch)

    def step(self, mark=None):
        return training_step(self.model, self.net, self.ema, self.opt, self.schedule, self.cfg, self.spec, self.stats,
                             self.weights, self.next_batch, 1e-4, 0.999, mark)

    def seconds_per_step(self, repeats: int, plain: bool = False) -> float:
        """Median over ``repeats`` timings of 3 steps each, without synchronisations inside; ``plain``: the step
        with the plain layers and the x0-hat losses on every scene (what the step was before it was made fast)."""
        with plain_step() if plain else contextlib.nullcontext():
            if plain:
                self.step()  # warm-up of the other path
            return self._seconds_per_step(repeats)

    def _seconds_per_step(self, repeats: int) -> float:
        times = []
        for _ in range(repeats):
            synchronize(self.device)
            t0 = time.perf_counter()
            for _ in range(3):
                self.step()
            synchronize(self.device)
            times.append((time.perf_counter() - t0) / 3)
        return sorted(times)[len(times) // 2]

    def shares(self, repeats: int) -> dict:
        """Each part's share of the step (synchronised between parts), and the x0-hat losses' share."""
        totals = dict.fromkeys(PARTS, 0.0)
        for _ in range(repeats):
            synchronize(self.device)
            last = [time.perf_counter()]

            def mark(part):
                synchronize(self.device)
                now = time.perf_counter()
                totals[part] += now - last[0]
                last[0] = now

            self.step(mark)
        whole = sum(totals.values())
        shares = {k: v / whole for k, v in totals.items()}
        shares["x0_hat_losses"] = self.penalty_seconds(repeats) / (whole / repeats)
        return shares

    def penalty_seconds(self, repeats: int) -> float:
        """The overlap and out-of-bound losses, forward and backward, on a batch's predicted x0 (here: x0 + noise)."""
        cfg, times = self.cfg, []
        for _ in range(repeats):
            b = self.next_batch()
            x0_hat = (b.x0 + 0.05 * b.noise).requires_grad_(True)
            synchronize(self.device)
            t0 = time.perf_counter()
            loss = (overlap_excess(self.spec, self.stats, b.extents, cfg.overlap_weight, cfg.overlap_max_timestep)
                    (x0_hat, b.x0, b.t)
                    + out_of_bound_excess(self.spec, self.stats, b.extents, b.points, cfg.out_of_bound_weight,
                                          cfg.out_of_bound_max_timestep)(x0_hat, b.x0, b.t)).mean()
            loss.backward()
            synchronize(self.device)
            times.append(time.perf_counter() - t0)
        return sorted(times)[len(times) // 2]

    def gpu_profile(self, steps: int = 3) -> dict:
        """On CUDA, per step: the kernels launched, the GPU's busy time and the host's time to queue the step (ms).
        Queueing about as long as the GPU is busy means the step is bound by launches, not by the GPU."""
        synchronize(self.device)
        t0 = time.perf_counter()
        for _ in range(steps):
            self.step()
        host_ms = (time.perf_counter() - t0) / steps * 1e3
        synchronize(self.device)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            for _ in range(steps):
                self.step()
            synchronize(self.device)
        kernels = [e for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA]
        return {"kernels_per_step": sum(e.count for e in kernels) / steps, "host_ms": host_ms,
                "gpu_busy_ms": sum(e.self_device_time_total for e in kernels) / steps / 1e3}

    def flops_per_room(self, reference: bool) -> float:
        """FLOPs of one forward and backward pass per room (torch's counter); ``reference``: of the plain step."""
        batch = self.next_batch()
        counter = FlopCounterMode(display=False)
        with plain_step() if reference else contextlib.nullcontext(), counter, torch.autocast(self.device.type, dtype=torch.bfloat16,
                                            enabled=self.cfg.precision == "bf16"):
            batch_loss(self.net, self.schedule, batch, self.cfg, self.spec, self.stats, self.weights).mean().backward()
        self.net.zero_grad(set_to_none=True)
        return counter.get_total_flops() / self.batch


@contextlib.contextmanager
def plain_step():
    """The step as plain layers: the PointNet's (B, P, F) activation formed, the floor tokens' keys and values
    projected, the x0-hat losses on every scene."""
    import agents.x0_losses as x0_losses

    with mock.patch.object(PointNetEncoder, "encode", PointNetEncoder.encode_reference), \
            mock.patch.object(Attention, "forward", Attention.forward_reference), \
            mock.patch.object(x0_losses, "on_rows", lambda mask, per_scene, *scenes: per_scene(*scenes) * mask):
        yield


def fits(preset: str, batch: int, device: torch.device, data, stats, max_step_seconds: float) -> bool:
    """Whether a step of ``batch`` rooms runs: in memory on a GPU, in under ``max_step_seconds`` on the CPU."""
    try:
        setup = Setup(preset, batch, device, data, stats, compile_=False,
                      precision="bf16" if device.type == "cuda" else "fp32")
        t0 = time.perf_counter()
        setup.step()
        synchronize(device)
        return device.type == "cuda" or time.perf_counter() - t0 < max_step_seconds
    except torch.OutOfMemoryError:
        return False
    finally:
        if device.type == "cuda":
            torch.cuda.empty_cache()


def largest_batch(preset: str, device: torch.device, data, stats, max_step_seconds: float, cap: int = 1 << 16) -> int:
    batch = 512
    while batch * 2 <= cap and fits(preset, batch * 2, device, data, stats, max_step_seconds):
        batch *= 2
    return batch


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    p.add_argument("--presets", default=None,
                   help="comma-separated presets (default small,paper on CUDA; small on the CPU, where a paper-size step "
                        "takes half a minute)")
    p.add_argument("--batches", default="512,max", help="comma-separated batch sizes and/or 'max' (default 512,max)")
    p.add_argument("--repeats", type=int, default=5, help="timings per row (default 5; each of 3 steps)")
    p.add_argument("--compile", action="store_true", help="also time the step with torch.compile (CUDA)")
    p.add_argument("--precisions", help="comma-separated fp32 / bf16 (default: fp32,bf16 on the CPU, bf16 on CUDA)")
    p.add_argument("--max-step-seconds", type=float, default=8.0,
                   help="on the CPU, 'max' is the largest batch whose step takes less (default 8)")
    p.add_argument("--rooms", type=int, default=2000, help="procedural bedrooms to draw batches from (default 2000)")
    p.add_argument("--json", help="write the rows to this file")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: torch sees no CUDA GPU here")
    layouts = generate_layouts("bedroom", args.rooms, seed=0)
    stats = stats_for_training(layouts, "bedroom", rotation_augment=True)
    stats = replace(stats, translation_frame="room")
    data = SceneTensors.from_layouts(layouts, get_room("bedroom").max_objects)
    precisions = (args.precisions or ("bf16" if device.type == "cuda" else "fp32,bf16")).split(",")
    if not set(precisions) <= {"fp32", "bf16"}:
        p.error(f"--precisions: fp32 and/or bf16, got {args.precisions!r}")
    references = ["fp32"] if device.type == "cpu" else []  # the float32 rate is the CPU rows' common reference
    matmul = {prec: matmul_flops(device, prec) for prec in dict.fromkeys(precisions + references)}
    print(f"{platform.processor() or platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"device {device}" + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""))
    print("matmul: " + ", ".join(f"{prec} {rate / 1e9:.1f} GFLOP/s" for prec, rate in matmul.items()))
    rows = []
    presets = args.presets or ("small,paper" if device.type == "cuda" else "small")
    for preset in presets.split(","):
        batches = []
        for b in args.batches.split(","):
            batches.append(largest_batch(preset, device, data, stats, args.max_step_seconds) if b == "max" else int(b))
        for batch, precision in ((b, prec) for b in dict.fromkeys(batches) for prec in precisions):
            for compile_ in ((False, True) if args.compile else (False,)):
                setup = Setup(preset, batch, device, data, stats, compile_, precision)
                setup.step()  # warm-up (compiles)
                setup.step()
                seconds = setup.seconds_per_step(args.repeats)
                plain_seconds = setup.seconds_per_step(args.repeats, plain=True) if not compile_ else None
                for prec in matmul:  # the best of the rates measured so far: a strict reference
                    matmul[prec] = max(matmul[prec], matmul_flops(device, prec))
                model_flops, executed = setup.flops_per_room(True), setup.flops_per_room(False)
                row = {"device": str(device), "preset": preset, "batch": batch, "precision": precision,
                       "compile": compile_, "rooms_per_s": batch / seconds, "flops_per_room": model_flops,
                       "executed_flops_per_room": executed, "matmul_flops_per_s": matmul[precision],
                       "fraction": batch / seconds * model_flops / matmul[precision],
                       "shares": setup.shares(args.repeats),
                       "plain_rooms_per_s": batch / plain_seconds if plain_seconds else None}
                if device.type == "cpu" and precision != "fp32":
                    row["fraction_of_fp32_matmul"] = batch / seconds * model_flops / matmul["fp32"]
                if device.type == "cuda":
                    row.update(setup.gpu_profile())
                rows.append(row)
                print(f"{preset:6s} batch {batch:6d} {precision}{' compiled' if compile_ else ''}: "
                      f"{row['rooms_per_s']:9.0f} rooms/s, {model_flops / 1e6:.0f} MFLOP/room (executed "
                      f"{executed / 1e6:.0f}), {row['fraction']:.1%} of the {precision} matmul rate"
                      + (f" ({row['fraction_of_fp32_matmul']:.1%} of the fp32 one)"
                         if "fraction_of_fp32_matmul" in row else "")
                      + (f"; {plain_seconds / seconds:.2f} x the plain step's {row['plain_rooms_per_s']:.0f} rooms/s"
                         if plain_seconds else "") + "; shares "
                      + ", ".join(f"{k} {v:.0%}" for k, v in row["shares"].items())
                      + (f"; {row['kernels_per_step']:.0f} kernels/step, GPU busy {row['gpu_busy_ms']:.1f} ms, "
                         f"queued in {row['host_ms']:.1f} ms" if "host_ms" in row else ""), flush=True)
                del setup
                if device.type == "cuda":
                    torch.cuda.empty_cache()
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
