"""Ship a paper task's stage-2 adapter from an ``iarcs train`` run: its exported LoRA weights in float16 (half the
size; the samples keep their classes and move by under 4 mm), the reward program it was trained with and the task's
prompt, laid out as an ``iarcs generate`` library entry in ``agents/checkpoints/<room>_small_tasks/<task>/``, with
``training.json``: the run's epochs and training time, with those of the runs it continued, if any (what
``experiments/cost_table.py`` charges an adapter; an offline fine-tuning of ``research/search_sft.py`` adds its time
from its ``tb/``, no epochs).

    .venv/bin/python experiments/ship_task_adapter.py out/train/t41_two_nightstands
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path


def train_seconds(run_dir: Path) -> float:
    """A run's training time: the span of its TensorBoard events (evaluations included), summed over its event
    files (one per start: the pause before a resumed run does not count)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    total = 0.0
    for path in sorted((run_dir / "tb").glob("events.out.tfevents.*")):
        events = EventAccumulator(str(path)).Reload()
        times = [e.wall_time for tag in events.Tags()["scalars"] for e in events.Scalars(tag)]
        total += max(times, default=events.FirstEventTimestamp()) - events.FirstEventTimestamp()
    return total


def training_runs(run_dir: Path) -> list[Path]:
    """The runs an adapter was trained through, first to last: a run whose ``init_adapter`` is another run's
    exported adapter (``RUN/adapters/NAME``) continues that run (a second phase)."""
    from agents.train import ADAPTERS_DIR, load_train_config

    init = Path(load_train_config(run_dir / "config.yaml").init_adapter or ".")
    earlier = init.parents[1] if len(init.parents) > 1 and init.parent.name == ADAPTERS_DIR else None
    return (training_runs(earlier) if earlier and (earlier / "config.yaml").exists() else []) + [run_dir]


def training_record(run_dir: Path) -> dict:
    """``training.json``: the run, its phases' epochs (``iarcs train`` runs, which checkpoint; an offline fine-tuning
    has none) and their training time."""
    from agents.train import CHECKPOINT_DIR, load_train_config

    runs = training_runs(run_dir)
    training = {"run": str(run_dir), "epochs": sum(load_train_config(r / "config.yaml").epochs for r in runs
                                                   if (r / CHECKPOINT_DIR).is_dir()),
                "train_seconds": round(sum(train_seconds(r) for r in runs), 1)}
    if len(runs) > 1:
        training["phases"] = [str(r) for r in runs]
    return training


def ship(run_dir: Path) -> Path:
    from safetensors.torch import load_file, save_file

    from agents.train import ADAPTERS_DIR, load_train_config, shipped_task_dir
    from iarcs_env.tasks import get_task

    cfg = load_train_config(run_dir / "config.yaml")
    task = get_task(cfg.task["checker"])
    source = run_dir / ADAPTERS_DIR / cfg.adapter
    if not (source / "adapter_config.json").exists():
        sys.exit(f"{run_dir} has no exported adapter {cfg.adapter!r} (let the run finish first)")
    dest = shipped_task_dir(cfg.room, task.name)
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(source, dest / "adapter")
    for weights in (dest / "adapter").rglob("*.safetensors"):  # with the reference adapter it builds on, if any
        save_file({k: v.half() for k, v in load_file(weights).items()}, weights)
    for card in (dest / "adapter").rglob("README.md"):  # peft's blank model-card template
        card.unlink()
    shutil.copytree(run_dir / "reward", dest / "reward")
    (dest / "constraint.txt").write_text(task.prompt + "\n")
    (dest / "training.json").write_text(json.dumps(training_record(run_dir), indent=1) + "\n")
    return dest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="an `iarcs train` run folder of a paper task's config")
    dest = ship(parser.parse_args().run)
    print(f"shipped to {dest}")


if __name__ == "__main__":
    main()
