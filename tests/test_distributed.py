"""Data-parallel training under real ``torchrun`` processes (2 CPU processes talking through gloo, whatever GPUs
the machine has; 2 GPUs through NCCL where there are two): averaged gradients, advantages over every rank's
scenes, one adapter on every rank, one run folder, resuming."""

import json
import os
import subprocess
import sys

import pytest
import torch

from iarcs_env.tasks import get_task
from rewards.memory import EvolutionMemory
from conftest import REPO, write_tiny_train_config


#: torchrun's own start-up can lose a race for a free port on a busy machine; that (and only that) is retried once.
PORT_RACE = ("DistNetworkError", "Address already in use", "RendezvousConnectionError")


def launch(*args: str, processes: int = 2) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc_per_node=processes ARGS`` from the repository root."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO / "tests")}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={processes}", *args]
    for _ in range(2):
        done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        if done.returncode == 0 or not any(s in done.stderr for s in PORT_RACE):
            break
    return done


def torchrun(*args: str, processes: int = 2) -> subprocess.CompletedProcess:
    done = launch(*args, processes=processes)
    assert done.returncode == 0, f"torchrun failed ({done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


def test_ranks_average_gradients_share_advantages_and_keep_one_adapter(tmp_path):
    from test_ddpo import make_model

    torchrun(str(REPO / "tests" / "distributed_worker.py"), str(tmp_path))
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in range(2)]

    # the mean of the two half-batch gradients is the whole batch's gradient, on both ranks
    assert any(float(g.abs().max()) > 0 for g in ranks[0]["averaged"])
    for rank in ranks:
        for avg, whole in zip(rank["averaged"], rank["whole"]):
            torch.testing.assert_close(avg, whole, rtol=1e-4, atol=1e-7)

    # the advantages are those one process computes over both ranks' rewards
    one = make_model().compute_advantages(torch.cat([r["rewards"] for r in ranks]),
                                          torch.cat([r["floor_index"] for r in ranks]))
    torch.testing.assert_close(torch.cat([r["advantages"] for r in ranks]), one)
    assert not torch.allclose(ranks[0]["advantages"], ranks[1]["advantages"])

    # the ranks collected different scenes but trained one adapter, which moved
    assert ranks[0]["epoch"] == ranks[1]["epoch"] == 2
    assert not torch.allclose(ranks[0]["scene"], ranks[1]["scene"])
    for name, value in ranks[0]["after"].items():
        torch.testing.assert_close(ranks[1]["after"][name], value, rtol=0, atol=0)
    assert any(not torch.equal(ranks[0]["before"][k], v) for k, v in ranks[0]["after"].items())

    # rank 0's reflection (a new task program, a new weight) reached rank 1
    from distributed_worker import NIGHTSTANDS

    assert ranks[1]["reward"] == ranks[0]["reward"] == {"code": NIGHTSTANDS,
                                                        "weights": {"collision": 1.0, "task": 2.5}}


def test_torchrun_train_writes_one_run_folder_and_resumes(tmp_path):
    config = write_tiny_train_config(tmp_path)
    done = torchrun("-m", "experiments.cli", "train", "--config", str(config), "--device", "cpu")
    assert "training on cpu, 2 processes of 8 scenes per rollout batch" in done.stdout, done.stdout + done.stderr
    assert done.stdout.count("DDPO-IS: 2 epochs") == 1, done.stdout  # rank 0 reports, once
    run = tmp_path / "run"
    assert (run / "adapters" / "stage1" / "adapter_config.json").exists()
    assert json.loads((run / "checkpoint" / "trainer.json").read_text())["epoch"] == 2
    evals = [json.loads(line) for line in (run / "eval.jsonl").read_text().splitlines()]
    assert [e["epoch"] for e in evals] == [1, 2]  # evaluated by rank 0 alone
    assert len([p for p in (run / "tb").iterdir() if p.name.startswith("events.out.tfevents")]) == 1

    done = torchrun("-m", "experiments.cli", "train", "--config", str(config), "--epochs", "3", "--device", "cpu")
    assert "resuming" in done.stdout, done.stdout + done.stderr
    assert json.loads((run / "checkpoint" / "trainer.json").read_text())["epoch"] == 3
    assert [json.loads(line)["epoch"] for line in (run / "eval.jsonl").read_text().splitlines()] == [1, 2, 3]


def test_torchrun_stage2_reflects_on_rank_0_only(tmp_path):
    config = write_tiny_train_config(tmp_path, adapter="two_nightstands", epochs=4, eval_every=2,
                                     task={"checker": "two_nightstands", "reflect_every": 2})
    torchrun("-m", "experiments.cli", "train", "--config", str(config), "--device", "cpu")
    run = tmp_path / "run"
    memory = json.loads((run / "reward_memory.json").read_text())
    assert [(e["kind"], e["epoch"]) for e in memory["entries"]] == [("synthesize", 0), ("reflect", 2), ("reflect", 4)]
    current = EvolutionMemory.open(run / "reward_memory.json", get_task("two_nightstands").prompt, "bedroom").current()
    assert (run / "reward" / "program.py").read_text() == current.code
    assert (run / "adapters" / "two_nightstands" / "adapter_config.json").exists()


def test_other_commands_refuse_to_run_under_torchrun(monkeypatch, tmp_path, capsys):
    from experiments.cli import main

    monkeypatch.setenv("WORLD_SIZE", "2")  # what torchrun sets in each process it starts
    assert main(["sample", "--num-scenes", "2", "--out", str(tmp_path / "s.json")]) == 2
    assert "iarcs sample runs in one process; only `iarcs train` and `iarcs pretrain` run data-parallel" in \
        capsys.readouterr().err
    assert not (tmp_path / "s.json").exists()


def test_torchrun_pretrain_writes_one_run_and_resumes(tmp_path):
    from agents.denoiser import ScenePrior
    from iarcs_env.datasets import save_layouts
    from test_pretrain import toy_bedrooms

    data = save_layouts(toy_bedrooms(40), tmp_path / "rooms.json")
    config = tmp_path / "pretrain.yaml"
    config.write_text(f"room: bedroom\ndataset: {data}\npreset: tiny\nbatch_size: 8\nsteps: 6\nlr: 3.0e-3\n"
                      "warmup_steps: 2\ncheckpoint_every: 3\nlog_every: 1\neval_every: 3\nval_scenes: 4\n"
                      f"tensorboard: true\nout: {tmp_path / 'run'}\n")
    done = torchrun("-m", "experiments.cli", "pretrain", "--config", str(config), "--device", "cpu")
    said = done.stdout + done.stderr
    assert "2 processes of 4 scenes per step" in done.stdout and done.stdout.count("step 6/6") == 1, said
    run = tmp_path / "run"
    logged = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in logged] == [1, 2, 3, 4, 5, 6]  # written by rank 0 alone
    assert all(r["loss"] > 0 for r in logged) and "val_loss_ema" in logged[-1]
    assert ScenePrior.load(run / "prior.pt").meta["step"] == 6

    done = torchrun("-m", "experiments.cli", "pretrain", "--config", str(config), "--steps", "8", "--device", "cpu")
    assert "resumed" in done.stdout and "step 8/8" in done.stdout, done.stdout + done.stderr
    assert [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()][-2:] == [7, 8]

    config.write_text(config.read_text().replace("batch_size: 8", "batch_size: 7"))
    failed = launch("-m", "experiments.cli", "pretrain", "--config", str(config), "--out", str(tmp_path / "b"),
                    "--device", "cpu")
    assert failed.returncode != 0
    assert "batch_size 7 does not split evenly over 2 processes; make it a multiple of 2" in failed.stderr, \
        failed.stderr[-3000:]


@pytest.mark.skipif(torch.cuda.device_count() < 2, reason=f"NCCL needs 2 CUDA GPUs; torch {torch.__version__} sees "
                                                           f"{torch.cuda.device_count()}")
def test_torchrun_train_on_two_gpus_over_nccl(tmp_path):
    config = write_tiny_train_config(tmp_path)
    done = torchrun("-m", "experiments.cli", "train", "--config", str(config), "--device", "cuda")
    assert "training on cuda:0, 2 processes of 8 scenes per rollout batch" in done.stdout, done.stdout + done.stderr
    assert json.loads((tmp_path / "run" / "checkpoint" / "trainer.json").read_text())["epoch"] == 2
