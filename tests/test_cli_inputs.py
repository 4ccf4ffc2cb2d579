"""Bad input to the command line never damages input files (issue 42): an ``--out`` that names an input is refused
with a message naming both flags, exit status 2, and the input left byte for byte as it was."""

from __future__ import annotations

import hashlib

import pytest

from experiments.cli import main

PROGRAM = "def reward(scene):\n    return scene.count('bed').float()\n"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("inputs")
    scenes = root / "scenes.json"
    assert main(["data", "generate", "--room", "bedroom", "--num-scenes", "3", "--seed", "1", "--out", str(scenes)]) == 0
    program = root / "reward.py"
    program.write_text(PROGRAM)
    return {"scenes": scenes, "program": program}


@pytest.mark.parametrize("argv, flag", [
    (["evaluate", "--scenes", "{scenes}", "--out", "{scenes}"], "--scenes"),
    (["reward", "score", "--program", "{program}", "--scenes", "{scenes}", "--out", "{scenes}"], "--scenes"),
    (["reward", "score", "--program", "{program}", "--scenes", "{scenes}", "--out", "{program}"], "--program"),
    (["sample", "--floors", "{scenes}", "--out", "{scenes}"], "--floors"),
    (["data", "render", "--in", "{scenes}", "--out", "{scenes}"], "--in"),
])
def test_an_output_that_is_an_input_is_refused(inputs, capsys, argv, flag):
    argv = [a.format(**inputs) for a in argv]
    before = {k: hashlib.sha256(p.read_bytes()).hexdigest() for k, p in inputs.items()}
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"is also the {flag} input" in err and "choose another output path" in err, err
    assert before == {k: hashlib.sha256(p.read_bytes()).hexdigest() for k, p in inputs.items()}
