"""Experiment configs: every shipped YAML loads, and an ablation is a short override of a base config."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.config import load_yaml_config, read_yaml_settings
from agents.pretrain import PretrainConfig
from agents.train import TrainConfig

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


def config_class(path: Path):
    return PretrainConfig if path.name.startswith("pretrain") else TrainConfig


@pytest.mark.parametrize("path", sorted(EXPERIMENTS.glob("*.yaml")) + sorted(EXPERIMENTS.glob("ablations/*.yaml")),
                         ids=lambda p: p.name)
def test_every_shipped_config_loads(path):
    cfg = load_yaml_config(config_class(path), path)
    assert cfg.out  # every experiment writes somewhere of its own


def test_every_ablation_is_an_override_of_a_base(tmp_path):
    for path in sorted(EXPERIMENTS.glob("ablations/*.yaml")):
        text = path.read_text()
        assert "\nbase: ../" in "\n" + text, path.name
        changes = [line for line in text.splitlines() if line and not line.startswith("#")]
        assert len(changes) <= 25, f"{path.name}: {len(changes)} lines; an ablation says only what it changes"


def test_an_override_merges_mappings_and_null_removes_a_setting(tmp_path):
    (tmp_path / "base.yaml").write_text("epochs: 300\nout: out/a\nddpo: {clip_range: 1.0e-4, kl_coef: 0.1}\n"
                                        "reward: {collision: 1.0, boundary: 1.0}\n")
    (tmp_path / "ablation.yaml").write_text("base: base.yaml\nout: out/b\nddpo: {kl_coef: null, x0_baseline: true}\n"
                                            "reward: {boundary: null}\n")
    settings = read_yaml_settings(tmp_path / "ablation.yaml")
    assert settings == {"epochs": 300, "out": "out/b", "ddpo": {"clip_range": 1.0e-4, "x0_baseline": True},
                        "reward": {"collision": 1.0}}
    cfg = load_yaml_config(TrainConfig, tmp_path / "ablation.yaml", epochs=5)
    assert cfg.epochs == 5 and cfg.ddpo == {"clip_range": 1.0e-4, "x0_baseline": True}


@pytest.mark.parametrize("text, message", [
    ("base: missing.yaml\n", "no config file at"),
    ("base: [a.yaml]\n", "base must be the path of another config"),
    ("base: loop.yaml\n", "its base configs form a loop"),
])
def test_a_bad_base_is_one_clear_error(tmp_path, text, message):
    (tmp_path / "loop.yaml").write_text(text)
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        read_yaml_settings(tmp_path / "loop.yaml")
