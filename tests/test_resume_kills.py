"""Resume is exact (issue 42): a training run killed with SIGKILL at 21 moments (at random, while a checkpoint is
being written, just after one was swapped in) and resumed each time ends with the same adapter, byte for byte on
the CPU, and the same evaluation log, as a run that never stopped."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import write_tiny_train_config

DRIVER = Path(__file__).parent / "resume_kill_driver.py"


@pytest.mark.slow
def test_a_run_killed_21_times_ends_as_one_that_never_stopped(tmp_path):
    config = write_tiny_train_config(tmp_path, epochs=8, eval_every=1, checkpoint_every=1)
    done = subprocess.run([sys.executable, str(DRIVER), str(config), "21", "0"], capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    kinds = [kind for kind, _ in result["kills"]]
    assert len(kinds) == 21 and {"random", "writing", "swapped"} <= set(kinds), result["kills"]
    assert result["final_status"] == 0
    assert result["adapters_equal"], result
    assert result["evals"]["killed"] == result["evals"]["uninterrupted"] == list(range(1, 9))
