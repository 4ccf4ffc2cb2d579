"""`iarcs augment` and datasets mixed with weights in pretraining (issue 39, Table 4)."""

from __future__ import annotations

import json

import pytest
import torch
import yaml

import experiments.commands.augment as augment
from agents.config import read_yaml_settings
from agents.pretrain_data import SceneTensors
from experiments.cli import main
from iarcs_env.datasets import load_layouts
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.rooms import get_room


def tensors(n: int, seed: int) -> SceneTensors:
    return SceneTensors.from_layouts(generate_layouts("bedroom", n, seed=seed), get_room("bedroom").max_objects)


def test_a_mix_draws_each_dataset_its_weights_share_and_rooms_alike_within_it():
    small, large = tensors(5, 1), tensors(20, 2)
    mixed = SceneTensors.mixed([(small, 1.0), (large, 3.0)])
    assert len(mixed) == 25 and torch.equal(mixed.labels[:5], small.labels)
    assert mixed.draw_weights.sum().item() == pytest.approx(1.0)
    draws = torch.multinomial(mixed.draw_weights, 200_000, replacement=True, generator=torch.Generator().manual_seed(0))
    counts = torch.bincount(draws, minlength=25).float() / len(draws)
    assert counts[5:].sum().item() == pytest.approx(0.75, abs=0.01)  # weight 3 against 1
    assert counts[:5].std() < 0.005 and counts[5:].std() < 0.003  # alike within a dataset
    assert mixed.to("cpu").draw_weights is not None and tensors(3, 1).to("cpu").draw_weights is None


@pytest.fixture
def tiny_recipe(tmp_path, monkeypatch):
    """The bedroom recipe made small: 40 procedural training rooms, batches of 8."""
    recipe = read_yaml_settings(augment.RECIPES["bedroom"])
    recipe.update(num_scenes=40, val_scenes=4, batch_size=8, log_every=1, eval_every=2, checkpoint_every=2,
                  precision="fp32")
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    monkeypatch.setitem(augment.RECIPES, "bedroom", path)
    monkeypatch.setattr(augment, "CHUNK", 3)
    monkeypatch.setenv("IARCS_CACHE_DIR", str(tmp_path / "cache"))
    return path


def test_augment_samples_the_priors_training_floors_and_resumes_the_same_rooms(tiny_recipe, tmp_path, capsys):
    out = tmp_path / "aug"
    assert main(["augment", "--room", "bedroom", "--num-scenes", "7", "--out", str(out), "--minutes", "0"]) == 0
    rooms = load_layouts(out / "scenes.json", "bedroom")
    floors = generate_layouts("bedroom", 7, seed=0)
    assert [r.floor.vertices.tolist() for r in rooms] == [f.floor.vertices.tolist() for f in floors]
    for room in rooms:  # back in the floor plan's own frame
        xmin, zmin, xmax, zmax = room.floor.bounds
        assert ((room.translations[:, 0] > xmin - 0.5) & (room.translations[:, 0] < xmax + 0.5)).all()
    assert len(load_layouts(out / "atiss", "bedroom")) == 7
    assert sorted(p.name for p in (out / "chunks").iterdir()) == ["0000.json", "0001.json", "0002.json"]
    finetune, control = (yaml.safe_load((out / name).read_text()) for name in ("finetune.yaml", "control.yaml"))
    assert finetune["extra_datasets"][0]["dataset"] == str((out / "scenes.json").resolve())
    assert control == {**finetune, "extra_datasets": [], "out": str(out / "control")}  # the data alone, else alike
    assert f"iarcs pretrain --config {out / 'control.yaml'} --stop-at STEPS" in capsys.readouterr().out
    before = json.loads((out / "scenes.json").read_text())["scenes"]
    (out / "chunks" / "0001.json").unlink()  # as if killed while sampling it
    capsys.readouterr()
    assert main(["augment", "--room", "bedroom", "--num-scenes", "7", "--out", str(out), "--minutes", "0"]) == 0
    assert "2 of 3 chunks already sampled" in capsys.readouterr().out
    assert json.loads((out / "scenes.json").read_text())["scenes"] == before


def test_augment_fine_tunes_the_prior_on_its_data_plus_the_rooms(tiny_recipe, tmp_path, capsys):
    out = tmp_path / "aug"
    assert main(["augment", "--room", "bedroom", "--num-scenes", "6", "--out", str(out), "--minutes", "0.1",
                 "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert "6 rooms of" in printed and "beside 36 of procedural" in printed  # 40 rooms less 4 held out
    cfg = yaml.safe_load((out / "finetune.yaml").read_text())
    assert cfg["init_from"] == "default" and cfg["lr"] == 3.0e-5 and cfg["ema_decay"] == 0.995
    assert cfg["extra_datasets"] == [{"dataset": str((out / "scenes.json").resolve()), "weight": pytest.approx(6 / 36)}]
    assert (out / "prior" / "prior.pt").exists() and (out / "prior" / "train_state.pt").exists()
    step = json.loads((out / "prior" / "metrics.jsonl").read_text().splitlines()[-1])["step"]
    assert f"iarcs pretrain --config {out / 'control.yaml'} --stop-at {step}" in printed


@pytest.mark.parametrize("argv, message", [
    (["--num-scenes", "0"], "--num-scenes must be in 1..40"),
    (["--num-scenes", "41"], "--num-scenes must be in 1..40"),
    (["--num-scenes", "5", "--weight", "-1"], "--weight > 0"),
    (["--num-scenes", "5", "--adapter", "agents/checkpoints/bedroom_small.pt"], "is a prior, not an adapter"),
])
def test_augment_refuses_bad_input_in_one_line(tiny_recipe, tmp_path, capsys, argv, message):
    assert main(["augment", "--room", "bedroom", "--out", str(tmp_path / "x"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


def test_extra_datasets_are_checked():
    from agents.pretrain import PretrainConfig

    for bad in ([{"dataset": "a.json"}], [{"dataset": "a.json", "weight": 0}], ["a.json"],
                [{"dataset": "a.json", "weight": 1, "share": 2}]):
        with pytest.raises(ValueError, match=r"extra_datasets\[0\] must be \{dataset: PATH, weight: W\}"):
            PretrainConfig(extra_datasets=bad)
