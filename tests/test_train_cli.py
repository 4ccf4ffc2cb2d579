"""`iarcs train`: a run from a YAML config, its run folder, resuming after a kill, sampling with the adapter."""

import json
import signal
import subprocess
import sys
import time

import pytest
import yaml

from agents.denoiser import ScenePrior
from experiments.cli import main
from conftest import REPO, perturb_zero_init, write_tiny_train_config


@pytest.fixture
def tiny_run_config(tmp_path):
    return write_tiny_train_config(tmp_path)


def test_train_writes_a_complete_run_folder_and_resumes(tiny_run_config, tmp_path, capsys):
    from experiments.ship_task_adapter import train_seconds

    started = time.time()
    assert main(["train", "--config", str(tiny_run_config)]) == 0
    run = tmp_path / "run"
    assert (run / "adapters" / "stage1" / "adapter_config.json").exists()
    assert json.loads((run / "checkpoint" / "trainer.json").read_text())["epoch"] == 2
    evals = [json.loads(l) for l in (run / "eval.jsonl").read_text().splitlines()]
    assert [e["epoch"] for e in evals] == [1, 2] and 0 <= evals[0]["Col_obj"] <= 1
    assert any(p.name.startswith("events.out.tfevents") for p in (run / "tb").iterdir())
    capsys.readouterr()
    # the device is not a setting of the run: a run resumes on another one (the CPU run on a GPU, where there is one)
    assert main(["train", "--config", str(tiny_run_config), "--epochs", "3", "--device", "auto"]) == 0
    assert "resuming" in capsys.readouterr().out
    assert json.loads((run / "checkpoint" / "trainer.json").read_text())["epoch"] == 3
    evals = [json.loads(l) for l in (run / "eval.jsonl").read_text().splitlines()]
    best = json.loads((run / "best" / "best.json").read_text())  # the best evaluation's adapter is kept
    top = max(evals, key=lambda e: e["reward"])
    assert best == {"epoch": top["epoch"], "key": "reward", "value": top["reward"]}
    weights = lambda folder: (folder / "adapter_model.safetensors").read_bytes()  # noqa: E731
    assert weights(run / "adapters" / "stage1") == weights(run / "checkpoint" / "adapter" / "stage1")  # the last
    cfg = yaml.safe_load(tiny_run_config.read_text())
    tiny_run_config.write_text(yaml.safe_dump({**cfg, "export": "best"}))
    assert main(["train", "--config", str(tiny_run_config), "--epochs", "3"]) == 0
    assert f"the best evaluation's: reward {top['reward']:.4g} at epoch {top['epoch']}" in capsys.readouterr().out
    assert weights(run / "adapters" / "stage1") == weights(run / "best" / "stage1")
    # the training time a shipped adapter records: its TensorBoard events' span, within the wall time of the runs
    assert 0 < train_seconds(run) <= time.time() - started

    out = tmp_path / "samples.json"
    assert main(["sample", "--checkpoint", str(run), "--num-scenes", "3", "--steps", "4", "--out", str(out)]) == 0
    assert len(json.loads(out.read_text())["scenes"]) == 3


def test_best_tolerance_keeps_only_evaluations_close_to_the_start(tmp_path, capsys):
    tolerance = {"Col_obj": 0.0, "R_out": 0.0, "mean_objects": 0.0}
    config = write_tiny_train_config(tmp_path, epochs=6, export="best", best_tolerance=tolerance,
                                     ddpo={"samples_per_floor": 4, "minibatch_size": 8, "learning_rate": 0.01})
    perturb_zero_init(ScenePrior.load(tmp_path / "prior.pt"), scale=0.3).save(tmp_path / "prior.pt")  # so it learns
    assert main(["train", "--config", str(config)]) == 0
    run = tmp_path / "run"
    evals = [json.loads(l) for l in (run / "eval.jsonl").read_text().splitlines()]
    assert [e["epoch"] for e in evals] == [0, 1, 2, 3, 4, 5, 6]  # the starting adapter is the reference
    start, best, rejected = evals[0], None, 0
    for e in evals[1:]:  # what the guard must have done, replayed from the log
        if best is None or e["reward"] > best["reward"]:
            if (e["Col_obj"] <= start["Col_obj"] and e["R_out"] <= start["R_out"]
                    and e["mean_objects"] >= start["mean_objects"]):
                best = e
            else:
                rejected += 1
    out = capsys.readouterr().out
    assert out.count("not kept as best") == rejected
    if best:
        assert json.loads((run / "best" / "best.json").read_text())["epoch"] == best["epoch"]
    else:
        assert not (run / "best").exists() and "no evaluation was kept as best" in out
    assert main(["train", "--config", str(config), "--epochs", "7"]) == 0  # resumed: the logged start is kept
    assert [json.loads(l)["epoch"] for l in (run / "eval.jsonl").read_text().splitlines()].count(0) == 1


def test_best_tolerance_directions():
    from agents.callbacks import EvalCallback

    cb = EvalCallback([], best_tolerance={"Col_obj": 0.02, "mean_objects": 0.5})
    cb.start = {"Col_obj": 0.30, "mean_objects": 3.0}
    assert cb._within_tolerance({"Col_obj": 0.31, "mean_objects": 2.6})      # worse, within the amounts
    assert cb._within_tolerance({"Col_obj": 0.10, "mean_objects": 5.0})      # better
    assert not cb._within_tolerance({"Col_obj": 0.33, "mean_objects": 3.0})  # more collisions
    assert not cb._within_tolerance({"Col_obj": 0.30, "mean_objects": 2.4})  # emptied rooms


def test_emptied_rooms_raise_one_clear_warning():
    from agents.callbacks import furniture_loss_warning

    first = {"epoch": 20, "mean_ground_objects": 2.53}
    assert furniture_loss_warning(first, {"epoch": 100, "mean_ground_objects": 1.72}) is None   # 68% kept
    message = furniture_loss_warning(first, {"epoch": 200, "mean_ground_objects": 0.61})
    assert "from 2.53 (epoch 20) to 0.61 (epoch 200)" in message and "class_presence" in message
    assert furniture_loss_warning({"epoch": 0}, {"epoch": 5, "mean_ground_objects": 0.0}) is None  # older logs


def test_a_killed_run_resumes_from_its_last_checkpoint(tiny_run_config, tmp_path):
    cfg = yaml.safe_load(tiny_run_config.read_text())
    cfg["epochs"], cfg["eval_every"] = 100000, 100000
    tiny_run_config.write_text(yaml.safe_dump(cfg))
    cmd = [sys.executable, "-m", "experiments.cli", "train", "--config", str(tiny_run_config)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = tmp_path / "run" / "checkpoint" / "trainer.json"
    deadline = time.time() + 120
    try:
        while time.time() < deadline:
            try:
                if json.loads(state.read_text())["epoch"] >= 3:
                    break
            except (OSError, ValueError, KeyError):  # not written yet, or being swapped in
                pass
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    from agents.ddpo import DDPO

    latest = DDPO.latest_checkpoint(tmp_path / "run" / "checkpoint")  # a kill mid-save leaves checkpoint.old
    killed_at = json.loads((latest / "trainer.json").read_text())["epoch"]
    assert killed_at >= 3
    done = subprocess.run(cmd + ["--epochs", str(killed_at + 2)], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"resuming {tmp_path / 'run'} at epoch {killed_at}" in done.stdout
    assert json.loads(state.read_text())["epoch"] == killed_at + 2


def test_bad_train_configs_are_clear(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("epoch: 3\n")
    assert main(["train", "--config", str(bad)]) == 2
    assert "unknown key 'epoch' (did you mean 'epochs'?)" in capsys.readouterr().err
    assert main(["train", "--config", str(tmp_path / "none.yaml")]) == 2
    assert "no config file" in capsys.readouterr().err
    bad.write_text("best_tolerance: {Col_ob: 0.1}\n")
    assert main(["train", "--config", str(bad)]) == 2
    assert "best_tolerance: unknown metric 'Col_ob'; choose from Col_obj" in capsys.readouterr().err
    bad.write_text("best_tolerance: {R_out: -1}\n")
    assert main(["train", "--config", str(bad)]) == 2
    assert "R_out must be a number >= 0" in capsys.readouterr().err
    bad.write_text("device: gpu\n")
    assert main(["train", "--config", str(bad)]) == 2
    assert f"{bad}: device 'gpu' is not one iARCS runs on; use auto, cpu, cuda or cuda:N" in capsys.readouterr().err


@pytest.mark.parametrize("path", sorted((REPO / "experiments").rglob("*.yaml")), ids=lambda p: p.stem)
def test_every_experiment_config_loads_and_its_reward_builds(path):
    """A typo in a shipped config (an unknown field, reward or reward option) fails here, not an hour into
    a run."""
    from agents.denoiser import ScenePrior
    from agents.pretrain import load_config
    from agents.train import load_train_config
    from iarcs_env.datasets.procedural import generate_layouts
    from iarcs_env.scene import SceneBatch
    from rewards import CompositeReward

    if path.stem.startswith("pretrain"):
        assert load_config(path).steps > 0
        return
    cfg = load_train_config(path)
    stats = ScenePrior.load_default(cfg.room).stats
    total, terms = CompositeReward.from_config(dict(cfg.reward), stats=stats)(
        SceneBatch.from_layouts(generate_layouts(cfg.room, 4, seed=0)))
    assert set(terms) == set(cfg.reward) and total.shape == (4,) and total.isfinite().all()


def test_sample_with_a_placement_adapter_keeps_the_priors_features(tmp_path):
    """`iarcs sample --checkpoint ADAPTER` samples as the policy does: the features the adapter leaves to the
    prior come from the prior (here: every class, since this adapter adapts translation and yaw only)."""
    import torch

    from agents.denoiser import ScenePrior
    from agents.policy import DiffusionPolicy
    from iarcs_env.datasets.procedural import generate_layouts

    policy = DiffusionPolicy(ScenePrior.load_default("bedroom"), adapter="placement", num_steps=4,
                             adapted=["translation", "yaw"])
    torch.manual_seed(0)
    with torch.no_grad():
        for name, p in policy.model.named_parameters():
            if "lora_B" in name:
                p.normal_(0, 0.2)
    folder = policy.save_adapter(tmp_path / "adapters")
    out = tmp_path / "samples.json"
    assert main(["sample", "--checkpoint", str(folder), "--num-scenes", "6", "--steps", "4", "--seed", "0",
                 "--out", str(out)]) == 0
    labels = [sorted(o["label"] for o in s["objects"]) for s in json.loads(out.read_text())["scenes"]]
    floors = [l.floor for l in generate_layouts("bedroom", 6, seed=0)]

    def sampled_labels(**kw):
        batch = policy.prior.sample(floors, num_steps=4, generator=torch.Generator().manual_seed(0), **kw)
        return [sorted(l.labels) for l in batch.to_layouts()]

    assert labels == sampled_labels(eps_fn=policy.eps)
    assert labels != sampled_labels()  # the LoRA model on every feature would pick other objects


def test_sample_adapter_names_a_shipped_adapter(tmp_path, capsys):
    """``--adapter stage1`` samples the shipped stage-1 adapter (the same scenes as its folder passed as
    --checkpoint); an adapter that is not shipped is refused with the list of those that are."""
    from agents.train import stage1_adapter_path

    by_name, by_path = tmp_path / "by_name.json", tmp_path / "by_path.json"
    common = ["sample", "--num-scenes", "4", "--steps", "4", "--seed", "3"]
    assert main([*common, "--adapter", "stage1", "--out", str(by_name)]) == 0
    assert main([*common, "--checkpoint", str(stage1_adapter_path("bedroom")), "--out", str(by_path)]) == 0
    scenes = [json.loads(p.read_text())["scenes"] for p in (by_name, by_path)]
    assert [s["objects"] for s in scenes[0]] == [s["objects"] for s in scenes[1]]
    capsys.readouterr()
    assert main([*common, "--adapter", "no_such_task", "--out", str(by_name)]) == 2
    err = capsys.readouterr().err
    assert "--adapter no_such_task" in err and "shipped: stage1" in err
    assert main([*common, "--adapter", "stage1", "--checkpoint", "x", "--out", str(by_name)]) == 2


def test_a_resumed_runs_training_time_leaves_out_the_pause(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    from experiments.ship_task_adapter import train_seconds

    for start in range(2):  # two starts of a run, one second apart
        writer = SummaryWriter(str(tmp_path / "tb"), filename_suffix=f".{start}")
        for epoch in range(2):
            writer.add_scalar("reward", 1.0, epoch)
            writer.flush()
            time.sleep(0.2)
        writer.close()
        time.sleep(1.0)
    assert 0.2 <= train_seconds(tmp_path) < 1.0


def test_a_second_phase_is_charged_with_the_run_it_continues(tmp_path):
    """A run whose init_adapter is another run's exported adapter continues it: both are its training runs, first
    to last; a run from the shipped stage-1 adapter has only itself."""
    from experiments.ship_task_adapter import training_runs

    first, second, fresh = tmp_path / "phase1", tmp_path / "phase2", tmp_path / "fresh"
    for run, init in ((first, "default"), (second, str(first / "adapters" / "reach_1m")), (fresh, "default")):
        run.mkdir()
        (run / "config.yaml").write_text(f"room: bedroom\nadapter: reach_1m\ninit_adapter: {init}\nepochs: 3\n")
    assert training_runs(second) == [first, second]
    assert training_runs(fresh) == [fresh]


def test_an_offline_fine_tuning_phase_is_charged_its_time_and_no_epochs(tmp_path):
    """A phase without a checkpoint folder (research/search_sft.py's run) adds the span of its tb/ and no epochs."""
    from torch.utils.tensorboard import SummaryWriter

    from experiments.ship_task_adapter import training_record

    tuned, trained = tmp_path / "sft", tmp_path / "rl"
    for run, init in ((tuned, "default"), (trained, str(tuned / "adapters" / "wheelchair"))):
        run.mkdir()
        (run / "config.yaml").write_text(f"room: bedroom\nadapter: wheelchair\ninit_adapter: {init}\nepochs: 40\n")
        writer = SummaryWriter(str(run / "tb"))
        for step in range(2):
            writer.add_scalar("loss", 1.0, step)
            writer.flush()
            time.sleep(0.3)
        writer.close()
    (trained / "checkpoint").mkdir()
    record = training_record(trained)
    assert record["epochs"] == 40 and record["phases"] == [str(tuned), str(trained)]
    assert 0.6 <= record["train_seconds"] < 3.0
