"""The cost of constraint-satisfying scenes (issue 38, item 4): for each paper task, seconds per 1,000 passing
scenes by rejection sampling from the prior (``iarcs sample --satisfying TASK``) against training the task's
adapter and then sampling from it (training included), and how diverse the passing scenes are both ways (SCA
of their renders against the data rooms that pass the same checker; 50% = indistinguishable).

    .venv/bin/python experiments/cost_table.py --work out/cost [--scenes 1000 4000] [--tasks reach_1m ...]
        [--ways prior adapter]

Floors and data rooms: ``iarcs data generate --room bedroom --num-scenes MAX --seed 777``; N scenes use its first
N floors. Both ways sample those floors with ``--satisfying`` (``--max-draws``, seed 0), timed as the commands
run (model loading included), on the threads OMP_NUM_THREADS allows. An adapter's training time is its runs'
TensorBoard spans, every phase (the shipped adapter's ``training.json``); a task without a shipped adapter has
rejection rows only. Writes WORK/cost.json and WORK/cost.md after every row, keeping the rows of earlier calls it
did not measure again.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IARCS = [str(Path(sys.executable).parent / "iarcs")]  # the virtual environment's command


def run_timed(args: list[str]) -> float:
    """Run an ``iarcs`` command; its wall-clock seconds."""
    t0 = time.perf_counter()
    subprocess.run(IARCS + args, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def passing_sca(layouts, reference, seed: int = 0) -> tuple[float, int]:
    """SCA of ``layouts`` against ``reference`` (both passing one checker) and the scenes per side it used."""
    from iarcs_env.distribution import render_set, sca

    n = min(len(layouts), len(reference))
    if n < 5:
        return float("nan"), n
    return sca(render_set(layouts), render_set(reference), seed=seed), n


def measure(task: str, scenes: int, floors: Path, reference: list, work: Path, max_draws: int,
            adapter: list[str] | None, train_seconds: float | None) -> dict:
    """One way of getting ``scenes`` passing scenes: rejection from the prior (``adapter`` None) or from an
    adapter (``adapter`` the ``iarcs sample`` arguments naming it; ``train_seconds`` its training)."""
    from iarcs_env.datasets import load_layouts

    way = "prior" if adapter is None else "adapter"
    out = work / f"{task}_{way}_{scenes}.json"
    seconds = run_timed(["sample", "--floors", str(floors), "--num-scenes", str(scenes), "--seed", "0",
                         "--satisfying", task, "--max-draws", str(max_draws), "--out", str(out)] + (adapter or []))
    meta = json.loads(out.read_text())["meta"]["satisfying"]
    kept = load_layouts(out, "bedroom")
    score, n = passing_sca(kept, reference)
    total = seconds + (train_seconds or 0.0)
    return {"task": task, "way": way, "scenes": scenes, "kept": meta["kept"], "drawn": meta["drawn"],
            "passed": meta["passed"], "sample_seconds": seconds, "train_seconds": train_seconds,
            "seconds_per_1000": 1000 * total / max(meta["kept"], 1), "SCA": score, "SCA_scenes": n}


def markdown(rows: list[dict]) -> str:
    lines = ["| task | scenes asked | way | kept | acceptance | sampling s | training s | s per 1,000 passing "
             "| SCA vs passing data (scenes) |", "|---|---:|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        train = f"{r['train_seconds']:.0f}" if r["train_seconds"] is not None else "–"
        lines.append(f"| {r['task']} | {r['scenes']} | {r['way']} | {r['kept']} | {r['passed'] / r['drawn']:.1%} "
                     f"| {r['sample_seconds']:.0f} | {train} | {r['seconds_per_1000']:.0f} "
                     f"| {100 * r['SCA']:.1f}% ({r['SCA_scenes']}) |")
    return "\n".join(lines) + "\n"


def main() -> None:
    from agents.train import shipped_adapters, shipped_task_dir
    from iarcs_env.datasets import load_layouts
    from iarcs_env.tasks import TASKS, task_results

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, required=True, help="folder for the floors, samples and the table")
    parser.add_argument("--scenes", type=int, nargs="+", default=[1000, 4000], help="scenes asked (default 1000 4000)")
    parser.add_argument("--tasks", nargs="+", default=[t for t in TASKS if TASKS[t].room == "bedroom"],
                        help="paper tasks (default: every bedroom task)")
    parser.add_argument("--max-draws", type=int, default=50, help="draws per floor plan (default 50)")
    parser.add_argument("--ways", nargs="+", choices=["prior", "adapter"], default=["prior", "adapter"],
                        help="rejection from the prior, from the shipped adapter, or both (default)")
    args = parser.parse_args()

    args.work.mkdir(parents=True, exist_ok=True)
    floors = args.work / "floors.json"
    if not floors.exists():
        run_timed(["data", "generate", "--room", "bedroom", "--num-scenes", str(max(args.scenes)), "--seed", "777",
                   "--out", str(floors)])
    data = load_layouts(floors, "bedroom")
    if len(data) < max(args.scenes):
        sys.exit(f"{floors} holds {len(data)} rooms, fewer than --scenes asks; delete it to generate {max(args.scenes)}")
    table = args.work / "cost.json"

    def record(row: dict) -> None:
        """Add ``row`` to the table at once (a later crash keeps it), replacing an earlier measurement of it."""
        key = lambda r: (r["task"], r["scenes"], r["way"])  # noqa: E731
        rows = [r for r in (json.loads(table.read_text()) if table.exists() else []) if key(r) != key(row)] + [row]
        rows.sort(key=lambda r: (list(TASKS).index(r["task"]), r["scenes"], r["way"] != "prior"))
        table.write_text(json.dumps(rows, indent=1))
        (args.work / "cost.md").write_text(markdown(rows))
        print(markdown([row]), flush=True)

    for task in args.tasks:
        reference = [r for r, ok in zip(data, task_results(task, data)) if ok]
        adapter, seconds = None, None
        if task in shipped_adapters("bedroom"):
            adapter = ["--adapter", task]
            seconds = json.loads((shipped_task_dir("bedroom", task) / "training.json").read_text())["train_seconds"]
        for n in args.scenes:
            if "prior" in args.ways:
                record(measure(task, n, floors, reference, args.work, args.max_draws, None, None))
            if adapter and "adapter" in args.ways:
                record(measure(task, n, floors, reference, args.work, args.max_draws, adapter, seconds))
    print(markdown(json.loads(table.read_text())) if table.exists() else "nothing measured")


if __name__ == "__main__":
    main()
