"""Every shipped checkpoint samples the same scenes for the same seed as when it was shipped: a refactor of the
denoiser, the schedule, the policy or the decoding that changes what a checkpoint samples fails here.

The reference samples are `tests/fixtures/shipped_samples.json` (procedural floors, so nothing from 3D-FRONT).
When a checkpoint is replaced on purpose, rewrite them:
`IARCS_UPDATE_SHIPPED_SAMPLES=1 .venv/bin/python -m pytest tests/test_shipped_checkpoints.py`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.denoiser import ScenePrior
from agents.train import load_stage1_policy, shipped_adapter_path, shipped_adapters, shipped_task_dir, stage1_adapter_path
from experiments.commands.prior import load_sampler
from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.tasks import get_task

FIXTURE = Path(__file__).parent / "fixtures" / "shipped_samples.json"
UPDATE = os.environ.get("IARCS_UPDATE_SHIPPED_SAMPLES") == "1"
TASK_ADAPTERS = [name for name in shipped_adapters("bedroom") if name != "stage1"]
CHECKPOINTS = [("bedroom", None), ("livingroom", None), ("diningroom", None),
               ("bedroom", "stage1"), ("diningroom", "stage1"),
               *(("bedroom", name) for name in TASK_ADAPTERS)]


def sample(room: str, adapter: str | None) -> dict:
    floors = [lay.floor for lay in generate_layouts(room, 3, seed=4242)]
    generator = torch.Generator().manual_seed(0)
    if adapter is None:
        batch = ScenePrior.load_default(room).sample(floors, generator=generator)
    elif adapter == "stage1":
        batch = load_stage1_policy(room).sample(floors, generator=generator)
    else:  # a task adapter, loaded and sampled as `iarcs sample --adapter TASK` does (its objects given, if any)
        _, policy = load_sampler(str(shipped_adapter_path(room, adapter)), room)
        batch = policy.sample(floors, generator=generator)
    return {"labels": [lay.labels for lay in batch.to_layouts()],
            "geometry": [np.concatenate([lay.translations, lay.half_sizes, lay.yaws[:, None]], 1).round(6).tolist()
                         for lay in batch.to_layouts()]}


@pytest.fixture(scope="module")
def reference() -> dict:
    return json.loads(FIXTURE.read_text()) if FIXTURE.exists() else {}


@pytest.mark.parametrize("room, adapter", CHECKPOINTS, ids=lambda v: v or "prior")
def test_a_shipped_checkpoint_samples_what_it_sampled_when_shipped(reference, room, adapter):
    if not ScenePrior.default_path(room).exists() or (adapter and not stage1_adapter_path(room).exists()):
        pytest.skip(f"no shipped {room} {adapter or 'prior'} in this installation")
    key = f"{room}/{adapter or 'prior'}"
    got = sample(room, adapter)
    if UPDATE:
        reference[key] = got
        FIXTURE.write_text(json.dumps(reference, indent=0) + "\n")
        return
    assert key in reference, f"no reference samples for {key}: see this file's docstring"
    want = reference[key]
    assert got["labels"] == want["labels"]
    for g, w in zip(got["geometry"], want["geometry"]):
        assert np.allclose(g, w, atol=1e-4), key


@pytest.mark.parametrize("task", TASK_ADAPTERS)
def test_a_shipped_task_adapter_carries_its_prompt_reward_and_training_time(task):
    folder = shipped_task_dir("bedroom", task)
    assert (folder / "constraint.txt").read_text().strip() == get_task(task).prompt
    assert list((folder / "reward").glob("*.py")), "the reward program it was trained with"
    training = json.loads((folder / "training.json").read_text())
    assert training["epochs"] > 0 and training["train_seconds"] > 60
