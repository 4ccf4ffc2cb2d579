"""Where a pretraining step's time goes on this machine: a ``torch.profiler`` trace of the full step that
``benchmarks/bench_pretrain.py`` times (the small preset, the shipped GPU recipe's losses), its operators by self
time per step, each with its input shapes.

    .venv/bin/python research/profile_pretrain_step.py [--precision fp32|bf16] [--batch 512] [--top 20]

What it showed (docs/results/benchmarks.md, "Pretraining"): before the cross-attention stopped projecting the 68
floor tokens, their key and value products, copies and zero-fills were a third of the step; in bfloat16 the
attention's backward took most of it.
"""

from __future__ import annotations

import argparse
import collections
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    import torch
    from torch.profiler import ProfilerActivity, profile

    import bench_pretrain as bench

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--precision", default="fp32", choices=("fp32", "bf16"))
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--steps", type=int, default=3, help="steps traced (default 3)")
    p.add_argument("--top", type=int, default=20, help="operators listed (default 20)")
    args = p.parse_args(argv)
    layouts = bench.generate_layouts("bedroom", 1000, seed=0)
    stats = replace(bench.stats_for_training(layouts, "bedroom", rotation_augment=True), translation_frame="room")
    data = bench.SceneTensors.from_layouts(layouts, bench.get_room("bedroom").max_objects)
    setup = bench.Setup("small", args.batch, torch.device("cpu"), data, stats, False, args.precision)
    setup.step()
    setup.step()
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        for _ in range(args.steps):
            setup.step()
    by_op = collections.Counter()
    for event in prof.key_averages():
        by_op[event.key] += event.self_cpu_time_total / args.steps / 1e3
    print(f"{args.precision}, batch {args.batch}: {sum(by_op.values()):.0f} ms of operator time per step (profiled)")
    for event in sorted(prof.key_averages(group_by_input_shape=True), key=lambda e: -e.self_cpu_time_total)[:args.top]:
        print(f"{event.self_cpu_time_total / args.steps / 1e3:8.1f} ms {event.count // args.steps:4d}x "
              f"{event.key[:45]:45s} {str(event.input_shapes)[:80]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
