"""Seconds per DDPO epoch in one process and data-parallel over P ``torchrun`` processes, as a speed-up ratio.

    .venv/bin/python benchmarks/bench_distributed.py [--scenes 128] [--processes 2] [--preset small]

Both runs do the same work per epoch: --scenes bedrooms rolled out with 20 DDIM steps, the universal reward,
and one pass of DDPO-IS updates in minibatches of --minibatch scenes. One process uses all --threads torch
threads; the P processes take --scenes / P scenes and --threads / P threads each, and average their LoRA
gradients after every backward pass (gloo on the CPU, NCCL on GPUs: agents/distributed.py). The reference is
the one-process epoch measured in the same run; the all-reduce's share of the distributed epoch is the cost
of the communication.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from agents import distributed
from bench_ddpo_epoch import make_algo

STEPS = 20


def epoch_seconds(preset: str, scenes: int, minibatch: int, epochs: int) -> dict:
    """Mean seconds of ``epochs`` DDPO epochs after one warm-up epoch, and the seconds in gradient all-reduce."""
    algo = make_algo(preset, scenes, minibatch, STEPS)
    reduce_seconds = [0.0]
    average = distributed.average_gradients

    def timed_average(params):
        t = time.perf_counter()
        average(params)
        reduce_seconds[0] += time.perf_counter() - t

    distributed.average_gradients = timed_average
    per_epoch = scenes * STEPS
    algo.learn(per_epoch)  # warm-up
    reduce_seconds[0] = 0.0
    t0 = time.perf_counter()
    algo.learn(per_epoch * (1 + epochs))
    seconds = (time.perf_counter() - t0) / epochs
    return {"epoch_s": seconds, "allreduce_s": reduce_seconds[0] / epochs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=128, help="scenes per epoch in all (default 128)")
    ap.add_argument("--minibatch", type=int, default=32, help="scenes per optimiser step in all (default 32)")
    ap.add_argument("--processes", type=int, default=2, help="torchrun processes P (default 2)")
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="torch threads in all (default: the cores)")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--epochs", type=int, default=2, help="timed epochs after a warm-up one (default 2)")
    ap.add_argument("--json", default="out/benchmarks/bench_distributed.json")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # one of the torchrun processes
    args = ap.parse_args()
    p = args.processes
    if args.scenes % (4 * p) or args.minibatch % p:
        raise SystemExit(f"--scenes must be a multiple of 4 x {p} and --minibatch of {p} (4 samples per floor plan)")

    if args.worker:
        distributed.setup("cpu")
        torch.set_num_threads(max(1, args.threads // p))
        row = epoch_seconds(args.preset, args.scenes // p, args.minibatch // p, args.epochs)
        if distributed.is_main():
            Path(args.json).write_text(json.dumps(row))
        distributed.cleanup()
        return

    torch.set_num_threads(args.threads)
    single = epoch_seconds(args.preset, args.scenes, args.minibatch, args.epochs)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    part = Path(args.json).with_suffix(".rank0.json")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={p}", __file__,
           "--worker", *sys.argv[1:], "--json", str(part)]
    subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": str(max(1, args.threads // p))})
    multi = json.loads(part.read_text())
    part.unlink()
    row = {"preset": args.preset, "scenes": args.scenes, "minibatch": args.minibatch, "threads": args.threads,
           "processes": p, "one_process_epoch_s": single["epoch_s"], "distributed_epoch_s": multi["epoch_s"],
           "speedup": single["epoch_s"] / multi["epoch_s"], "allreduce_share": multi["allreduce_s"] / multi["epoch_s"]}
    print(f"{args.preset}, {args.scenes} scenes per epoch, {args.threads} threads in all")
    print(f"  1 process : {row['one_process_epoch_s']:.1f} s per epoch (the reference)")
    print(f"  {p} processes: {row['distributed_epoch_s']:.1f} s per epoch = {row['speedup']:.2f}x the reference; "
          f"gradient all-reduce {100 * row['allreduce_share']:.1f}% of it")
    Path(args.json).write_text(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
