"""Bad input to the command line (issue 42): an ``--out`` that names an input is refused with a message naming both
flags, exit status 2, and the input left byte for byte as it was; flags and configs whose numbers would run and
write nonsense are refused before anything runs; values the sandbox clips are counted, not silently changed."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from experiments.cli import main
from test_datasets_io import BAD_SCENES

REPO = Path(__file__).resolve().parents[1]

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
    (["data", "export", "--in", "{scenes}", "--out", "{scenes}"], "--in"),
])
def test_an_output_that_is_an_input_is_refused(inputs, capsys, argv, flag):
    argv = [a.format(**inputs) for a in argv]
    before = {k: hashlib.sha256(p.read_bytes()).hexdigest() for k, p in inputs.items()}
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"is also the {flag} input" in err and "choose another output path" in err, err
    assert before == {k: hashlib.sha256(p.read_bytes()).hexdigest() for k, p in inputs.items()}


@pytest.mark.parametrize("argv, message", [
    (["sample", "--eta", "nan", "--num-scenes", "2", "--out", "{root}/s.json"], "--eta: expected a finite number"),
    (["sample", "--guidance", "inf", "--num-scenes", "2", "--out", "{root}/s.json"], "--guidance: expected a finite"),
    (["evaluate", "--scenes", "{scenes}", "--cell=-inf", "--out", "{root}/e.json"], "--cell: expected a finite number"),
    (["data", "generate", "--room", "bedroom", "--flaw-rate", "NaN", "--out", "{root}/g.json"], "--flaw-rate"),
])
def test_flags_that_are_not_finite_numbers_are_refused(inputs, capsys, argv, message):
    argv = [a.format(root=inputs["scenes"].parent, **inputs) for a in argv]
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and message in capsys.readouterr().err
    assert not (inputs["scenes"].parent / "s.json").exists() and not (inputs["scenes"].parent / "g.json").exists()


@pytest.mark.parametrize("setting, message", [("epochs: -5", "epochs must be a positive whole number, got -5"),
                                              ("eval_every: 0", "eval_every must be a positive whole number"),
                                              ("eta: .nan", "eta must be a number in [0, 1]")])
def test_a_training_config_that_would_do_nothing_is_refused(tmp_path, capsys, setting, message):
    config = tmp_path / "run.yaml"
    config.write_text((REPO / "experiments" / "stage1_bedroom_quick.yaml").read_text() + f"\n{setting}\n")
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "run")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_scores_clipped_by_the_sandbox_are_counted(inputs, tmp_path, capsys):
    program = tmp_path / "big.py"
    program.write_text("def reward(scene):\n    return torch.full((scene.batch_size,), 10000.0)\n")
    out = tmp_path / "scores.json"
    assert main(["reward", "score", "--program", str(program), "--scenes", str(inputs["scenes"]), "--out", str(out)]) == 0
    assert "3 values beyond +-10 clipped to it" in capsys.readouterr().out


def test_an_output_under_a_file_is_a_one_line_error(inputs, capsys):
    out = inputs["program"] / "scenes.json"  # under a file
    assert main(["data", "generate", "--room", "bedroom", "--num-scenes", "2", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == f"iarcs: error: {inputs['program']} is a file, not a folder: choose an output path that is not under it"


def test_a_torn_last_line_of_a_log_is_dropped_with_a_warning(tmp_path):
    from agents.config import read_jsonl

    log = tmp_path / "eval.jsonl"
    log.write_text('{"epoch": 1, "success": 0.5}\n{"epoch": 2, "succ')
    warnings = []
    assert read_jsonl(log, warn=warnings.append) == [{"epoch": 1, "success": 0.5}]
    assert "torn last line 2" in warnings[0] and str(log) in warnings[0]
    log.write_text('{"epoch": 1}\n{"epo\n{"epoch": 3}\n')
    with pytest.raises(ValueError, match=r"eval.jsonl line 2 is not JSON"):
        read_jsonl(log)


#: Every command that reads layouts, with where the bad file goes ({bad}) and where it writes ({root}).
READERS = [
    ["evaluate", "--scenes", "{bad}", "--out", "{root}/r.json"],
    ["reward", "score", "--program", "{program}", "--scenes", "{bad}", "--out", "{root}/r.json"],
    ["sample", "--floors", "{bad}", "--out", "{root}/r.json"],
    ["data", "stats", "--in", "{bad}"],
    ["data", "render", "--in", "{bad}", "--out", "{root}/r"],
    ["data", "export", "--in", "{bad}", "--out", "{root}/r"],
    ["data", "convert", "--in", "{bad}", "--out", "{root}/r"],
]


@pytest.mark.parametrize("scene, message", BAD_SCENES, ids=[f"bad{k}" for k in range(len(BAD_SCENES))])
@pytest.mark.parametrize("argv", READERS, ids=lambda argv: "_".join(argv[:2]))
def test_no_command_takes_a_bad_scene_as_data(inputs, tmp_path, capsys, argv, scene, message):
    """Each bad scene through each command: exit 2, one line naming the file, the scene and the problem, nothing
    written, the input untouched."""
    import json
    import re

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"scenes": [scene]}))
    before = bad.read_bytes()
    argv = [a.format(bad=bad, root=tmp_path, **inputs) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("iarcs: error: ") and "Traceback" not in err and str(bad) in err and re.search(message, err)
    assert bad.read_bytes() == before and not (tmp_path / "r.json").exists() and not (tmp_path / "r").exists()


def test_a_bug_shows_its_traceback_and_how_to_report_it(monkeypatch, capsys):
    import experiments.commands.info as info

    def broken(args):
        raise RuntimeError("an internal inconsistency")

    monkeypatch.setattr(info, "cmd_info", broken)
    assert main(["info"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and "RuntimeError: an internal inconsistency" in err and "please report it" in err
    monkeypatch.setattr(info, "cmd_info", lambda args: (_ for _ in ()).throw(ValueError("a user's mistake")))
    assert main(["info"]) == 2
    assert capsys.readouterr().err == "iarcs: error: a user's mistake\n"  # one line
    monkeypatch.setenv("IARCS_TRACEBACK", "1")
    assert main(["info"]) == 2
    assert "Traceback" in capsys.readouterr().err  # on request
