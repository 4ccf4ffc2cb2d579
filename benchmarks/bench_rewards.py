"""Throughput of the batched universal rewards and metrics against the per-pair shapely reference.

    .venv/bin/python benchmarks/bench_rewards.py [--batch 256] [--repeats 5] [--out out/benchmarks/bench_rewards.json]

Scenes: the first ``--batch`` real bedrooms of ``../shared/data/3dfront/bedroom_val.json`` when present,
otherwise procedural bedrooms. Both sides run single-threaded (torch.set_num_threads(1)), in this one
process; the batched side is timed as the best of ``--repeats`` warm runs (floor pieces are cached per
floor plan after the first call, as they are in training where floor plans repeat), the reference once.
Targets: >= 50x for collision + boundary, >= 10x for accessibility and walkability.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository's packages (never `import benchmarks`: torchrl ships one)

import torch  # noqa: E402

from iarcs_env.walkable import free_space  # noqa: E402
from iarcs_env.metrics import batch_float64, evaluate_batch  # noqa: E402
from rewards import accessibility_reward, boundary_reward, collision_reward  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "3dfront" / "bedroom_val.json"


def _reference():
    spec = importlib.util.spec_from_file_location("shapely_reference", ROOT / "tests" / "shapely_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _scenes(n: int):
    if REAL.exists():
        from iarcs_env.datasets import load_layouts

        return load_layouts(REAL)[:n], f"real 3D-FRONT bedrooms ({REAL.name})"
    try:
        from iarcs_env.datasets.procedural import generate_layouts

        return generate_layouts("bedroom", n, seed=0), "procedural bedrooms"
    except ImportError:
        sys.path.insert(0, str(ROOT / "tests"))
        from scene_factory import random_layouts

        return random_layouts(n, seed=0), "random test bedrooms (tests/scene_factory.py)"


def best_of(fn, repeats: int) -> float:
    fn()  # warm up (lazy torch init, floor-piece cache)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def once(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default=str(ROOT / "out" / "benchmarks" / "bench_rewards.json"))
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    ref = _reference()
    layouts, source = _scenes(args.batch)
    batch = batch_float64(layouts)
    centred = [lay.centred() for lay in layouts]
    n = len(layouts)
    print(f"{n} scenes: {source}; {int(batch.mask.sum())} objects; torch {torch.__version__}, 1 thread, "
          f"{platform.processor() or platform.machine()}")

    rows = []

    def bench(name, batched, reference, target):
        tb = best_of(batched, args.repeats)
        tr = once(reference)
        rows.append({"name": name, "batched_s": tb, "reference_s": tr, "batched_scenes_per_s": n / tb,
                     "reference_scenes_per_s": n / tr, "speedup": tr / tb, "target": target})
        print(f"  {name:<34} batched {1e3 * tb:8.1f} ms ({n / tb:9.0f} scenes/s)   reference {1e3 * tr:8.1f} ms "
              f"({n / tr:7.0f} scenes/s)   speed-up {tr / tb:6.1f}x (target {target}x)")

    bench("collision reward", lambda: collision_reward(batch), lambda: [ref.collision_reward(l) for l in centred], 50)
    bench("boundary reward", lambda: boundary_reward(batch), lambda: [ref.boundary_reward(l) for l in centred], 50)
    bench("collision + boundary rewards", lambda: (collision_reward(batch), boundary_reward(batch)),
          lambda: [(ref.collision_reward(l), ref.boundary_reward(l)) for l in centred], 50)
    bench("accessibility reward (0.1 m grid)", lambda: accessibility_reward(batch),
          lambda: [ref.accessibility_reward(l, cell=0.1) for l in centred], 10)
    bench("accessibility reward (0.05 m grid)", lambda: accessibility_reward(batch, cell=0.05),
          lambda: [ref.accessibility_reward(l, cell=0.05) for l in centred], 10)
    bench("walkability + reach (0.05 m grid)",
          lambda: free_space(batch.floors, batch.translations, batch.half_sizes, batch.yaws,
                                 batch.ground_mask, cell=0.05, reach=True),
          lambda: [ref.walkable(l, 0.05) for l in centred], 10)
    bench("all five metrics (evaluate_batch)", lambda: evaluate_batch(batch), lambda: ref.metrics(centred), 10)

    ok = all(r["speedup"] >= r["target"] for r in rows)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"scenes": n, "source": source, "threads": 1, "rows": rows,
                               "targets_met": ok}, indent=1))
    print(f"targets met: {ok}; results: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
