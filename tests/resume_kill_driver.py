"""Driver of tests/test_resume_kills.py (run as its own process): trains a tiny run uninterrupted, then the same run
killed with SIGKILL at many moments and resumed each time, and prints what both ended with as JSON.

Children are forked from this process after its imports (one thread, so forking is safe), so a kill costs no
start-up: ``python tests/resume_kill_driver.py CONFIG.yaml KILLS SEED``."""

from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import sys
import time
from pathlib import Path

import torch

torch.set_num_threads(1)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import yaml  # noqa: E402

from experiments.cli import main  # noqa: E402


def start(config: Path) -> int:
    pid = os.fork()
    if pid == 0:  # the child: one `iarcs train`, quiet, then exit without running the parent's clean-ups
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        code = 1
        try:
            code = main(["train", "--config", str(config)])
        finally:
            os._exit(code)
    return pid


def finished(pid: int) -> bool:
    done, status = os.waitpid(pid, os.WNOHANG)
    return done == pid


def epoch_of(run: Path) -> int:
    try:
        return json.loads((run / "checkpoint" / "trainer.json").read_text())["epoch"]
    except (OSError, ValueError, KeyError):
        return -1


def kill_at(pid: int, run: Path, kind: str, rng: random.Random) -> bool:
    """Kill ``pid`` at a moment of ``kind``; False when it finished first."""
    ckpt = run / "checkpoint"
    deadline = time.monotonic() + 60
    if kind == "random":
        until = time.monotonic() + rng.uniform(0.0, 1.5)
        while time.monotonic() < until:
            if finished(pid):
                return False
            time.sleep(0.002)
    else:  # "writing": while a checkpoint is being written; "swapped": just after one was swapped in
        before = epoch_of(run)
        while time.monotonic() < deadline:
            if kind == "writing" and (ckpt.with_name("checkpoint.tmp").exists() or ckpt.with_name("checkpoint.old").exists()):
                break
            if kind == "swapped" and epoch_of(run) > before:
                break
            if finished(pid):
                return False
            time.sleep(0.0005)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    return True


def adapter(run: Path) -> str:
    return hashlib.sha256((run / "adapters" / "stage1" / "adapter_model.safetensors").read_bytes()).hexdigest()


def evals(run: Path) -> list[int]:
    return [json.loads(line)["epoch"] for line in (run / "eval.jsonl").read_text().splitlines() if line.strip()]


def main_driver(config: Path, kills: int, seed: int) -> dict:
    rng = random.Random(seed)
    base = yaml.safe_load(config.read_text())
    runs = {}
    for name in ("uninterrupted", "killed"):
        cfg = dict(base, out=str(config.parent / name))
        path = config.parent / f"{name}.yaml"
        path.write_text(yaml.safe_dump(cfg))
        runs[name] = (path, Path(cfg["out"]))
    path, run = runs["uninterrupted"]
    os.waitpid(start(path), 0)
    path, run = runs["killed"]
    moments = []
    while len(moments) < kills:
        kind = ("random", "writing", "swapped")[len(moments) % 3]
        if not kill_at(start(path), run, kind, rng):
            break  # it finished before the kill: nothing left to interrupt
        moments.append((kind, epoch_of(run)))
    _, status = os.waitpid(start(path), 0)
    return {"kills": moments, "final_status": status,
            "adapters_equal": adapter(runs["uninterrupted"][1]) == adapter(run),
            "evals": {name: evals(r) for name, (_, r) in runs.items()}}


if __name__ == "__main__":
    print(json.dumps(main_driver(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]))))
