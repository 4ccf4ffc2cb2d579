"""Stage 2: the reward evolution memory, a short task run with reflection that resumes with its memory, and
the command line around the agent (`iarcs reward synthesize|score`, `iarcs generate`)."""

import json

import pytest
import yaml

from experiments.cli import main
from iarcs_env.datasets import load_layouts
from iarcs_env.tasks import task_results
from rewards.memory import EvolutionMemory
from rewards.proposal import RewardProposal
from conftest import write_tiny_train_config

PROMPT = "A bedroom with 2 night tables on either side of the bed"


def proposal(code="def reward(scene):\n    return scene.count('nightstand')\n", **kw):
    return RewardProposal(constraint=PROMPT, reasoning="r", decomposition=["d"], code=code, **kw)


def test_memory_keeps_attempts_and_outcomes_and_survives_a_restart(tmp_path):
    path = tmp_path / "reward_memory.json"
    mem = EvolutionMemory.open(path, PROMPT, "bedroom")
    assert mem.current() is None and mem.stages() == 0
    mem.record("synthesize", 0, proposal(weight=2.0), accepted=True)
    mem.record("reflect", 10, proposal(code="bad"), accepted=False, message="SyntaxError",
               outcome={"epoch": 10, "task_success": [0.1, 0.1]})
    again = EvolutionMemory.open(path, PROMPT, "bedroom")
    assert again.current().weight == 2.0  # the rejected program never becomes current
    assert again.stages() == 1
    history = again.history()
    assert [h["accepted"] for h in history] == [True, False]
    assert history[0]["outcome"] == [{"epoch": 10, "task_success": [0.1, 0.1]}]  # feedback while in use
    assert history[1]["outcome"] == [] and again.task_success_history() == [0.1, 0.1]
    again.record("reflect", 20, proposal(code="def reward(scene):\n    return scene.count('bed')\n"), accepted=True)
    again.forget_after(10)  # resuming from the epoch-10 checkpoint: the epoch-20 reflection never happened
    assert "nightstand" in EvolutionMemory.open(path, PROMPT, "bedroom").current().code
    with pytest.raises(ValueError, match="another constraint"):
        EvolutionMemory.open(path, "A wheelchair-accessible bedroom", "bedroom")


@pytest.fixture
def tiny_task_config(tmp_path):
    return write_tiny_train_config(tmp_path, adapter="two_nightstands", epochs=4, eval_every=2,
                                   task={"checker": "two_nightstands", "reflect_every": 2})


def test_a_task_run_reflects_records_its_memory_and_resumes_with_it(tiny_task_config, tmp_path, capsys):
    assert main(["train", "--config", str(tiny_task_config)]) == 0
    run = tmp_path / "run"
    memory = json.loads((run / "reward_memory.json").read_text())
    assert memory["constraint"] == PROMPT
    kinds = [(e["kind"], e["epoch"]) for e in memory["entries"]]
    assert kinds == [("synthesize", 0), ("reflect", 2), ("reflect", 4)]
    first = memory["entries"][0]
    assert first["proposal"]["source"] == "offline" and "def reward(scene)" in first["proposal"]["code"]
    window = first["outcomes"][0]  # feedback while the first program was in use: rollouts of epochs 1 and 2
    assert window["epoch"] == 2 and len(window["task_success"]) == 2 and "task" in window["component_stats"]
    assert (run / "reward" / "program.py").read_text() == EvolutionMemory.open(
        run / "reward_memory.json", PROMPT, "bedroom").current().code
    evals = [json.loads(l) for l in (run / "eval.jsonl").read_text().splitlines()]
    assert all(0 <= e["task_success_two_nightstands"] <= 1 and "reward_task" in e for e in evals)
    assert (run / "adapters" / "two_nightstands" / "adapter_config.json").exists()

    capsys.readouterr()
    assert main(["train", "--config", str(tiny_task_config), "--epochs", "6"]) == 0
    out = capsys.readouterr().out
    assert "resuming" in out and "current program" in out  # no new synthesis: the memory's program
    entries = json.loads((run / "reward_memory.json").read_text())["entries"]
    assert [e["epoch"] for e in entries] == [0, 2, 4, 6]


def test_reward_synthesize_and_score_from_the_command_line(tmp_path, capsys):
    program = tmp_path / "two_nightstands.py"
    assert main(["reward", "synthesize", "--room", "bedroom", "--constraint", PROMPT, "--out", str(program)]) == 0
    meta = json.loads(program.with_suffix(".json").read_text())
    assert meta["reasoning"] and meta["decomposition"] and "def reward(scene)" in program.read_text()

    from iarcs_env.datasets import save_layouts
    from iarcs_env.datasets.procedural import generate_layouts

    layouts = generate_layouts("bedroom", 10, seed=3)
    save_layouts(layouts, tmp_path / "scenes.json")
    counting = tmp_path / "count.py"
    counting.write_text("def reward(scene):\n    return scene.count('nightstand')\n")
    scores = tmp_path / "scores.json"
    assert main(["reward", "score", "--program", str(counting), "--scenes", str(tmp_path / "scenes.json"),
                 "--out", str(scores), "--batch-size", "4"]) == 0
    assert json.loads(scores.read_text()) == [float(l.labels.count("nightstand")) for l in layouts]
    assert main(["reward", "score", "--program", str(program), "--scenes", str(tmp_path / "scenes.json"),
                 "--out", str(scores)]) == 0
    values = json.loads(scores.read_text())
    assert len(values) == 10 and all(isinstance(v, float) for v in values)


def test_reward_commands_report_bad_input_clearly(tmp_path, capsys, monkeypatch):
    assert main(["reward", "score", "--program", str(tmp_path / "missing.py"), "--scenes", "x.json",
                 "--out", str(tmp_path / "s.json")]) == 2
    assert "no reward program" in capsys.readouterr().err
    assert main(["reward", "synthesize", "--constraint", "  ", "--out", str(tmp_path / "p.py")]) == 2
    assert "empty" in capsys.readouterr().err
    for var in ("GEMINI_API_KEY", "GOOGLE_API_KEY"):
        monkeypatch.delenv(var, raising=False)
    assert main(["reward", "synthesize", "--constraint", PROMPT, "--model", "gemini/gemini-2.5-pro",
                 "--out", str(tmp_path / "p.py")]) == 2
    assert "GEMINI_API_KEY" in capsys.readouterr().err  # no traceback, the variable to set
    assert main(["reward", "synthesize", "--constraint", "a bedroom with a purple unicorn",
                 "--out", str(tmp_path / "p.py")]) == 2
    assert "not understood: purple unicorn" in capsys.readouterr().err


def test_a_request_whose_meaning_was_not_understood_is_refused_unless_allowed(tmp_path, capsys):
    """The planner does not read a quantifier on the reference of "on the left of": a program rewarding a nightstand
    left of some bed would ask less than the request, so the command refuses (exit 2) and says what to do;
    --allow-partial writes it, marked partial."""
    request = "A bedroom with a nightstand on the left of every bed"
    program = tmp_path / "every.py"
    assert main(["reward", "synthesize", "--constraint", request, "--out", str(program)]) == 2
    err = capsys.readouterr().err
    assert "did not understand 'every'" in err and "--model" in err and "--allow-partial" in err
    assert not program.exists()
    assert main(["reward", "synthesize", "--constraint", request, "--out", str(program), "--allow-partial"]) == 0
    assert "PARTIAL" in capsys.readouterr().out
    meta = json.loads(program.with_suffix(".json").read_text())
    assert meta["partial"] is True and meta["not_understood"] == ["every"]
    assert "# PARTIAL: written without every" in program.read_text()
    # the words it now reads: facing away is written, not refused
    away = tmp_path / "away.py"
    assert main(["reward", "synthesize", "--constraint", "A bedroom where the desk faces away from the bed",
                 "--out", str(away)]) == 0
    meta = json.loads(away.with_suffix(".json").read_text())
    assert meta["partial"] is False and meta["not_understood"] == [] and "desk_away_bed" in away.read_text()
    # a word that does not change the meaning is reported, not refused
    assert main(["reward", "synthesize", "--constraint", "A cozy bedroom with a double bed",
                 "--out", str(tmp_path / "cozy.py")]) == 0
    assert json.loads((tmp_path / "cozy.json").read_text())["partial"] is False


def test_training_refuses_a_partial_program_unless_told(tmp_path):
    from agents.stage2 import TaskConfig, setup_task_reward

    task = TaskConfig(constraint="A bedroom where not every chair faces the desk", reflect_every=0)
    with pytest.raises(ValueError, match=r"did not understand 'not'"):
        setup_task_reward(task, "bedroom", tmp_path / "run")
    reward, agent, memory, proposal = setup_task_reward(
        TaskConfig(constraint=task.constraint, reflect_every=0, allow_partial=True), "bedroom", tmp_path / "run2")
    try:
        assert proposal.partial and memory.current().partial
    finally:
        reward.close()


def test_generate_trains_once_then_reuses_the_adapter(tmp_path, monkeypatch, capsys):
    import shutil

    import agents.train

    monkeypatch.setenv("IARCS_HOME", str(tmp_path / "home"))
    monkeypatch.setattr(agents.train, "shipped_task_dir", lambda room, task: tmp_path / "shipped" / task)
    args = ["generate", "--room", "bedroom", "--constraint", PROMPT, "--num-scenes", "4", "--epochs", "1"]
    assert main(args + ["--out", str(tmp_path / "a")]) == 0
    out = tmp_path / "a"
    assert len(json.loads((out / "scenes.json").read_text())["scenes"]) == 4
    assert (out / "atiss" / "dataset_stats.txt").exists() and (out / "renders_1.png").exists()
    report = (out / "report.md").read_text()
    assert "def reward(scene)" in report and "task success" in report  # the prompt is a paper task's
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"prior", "stage 1", "with the task adapter"}
    assert 0 <= metrics["with the task adapter"]["task_success"] <= 1
    capsys.readouterr()
    assert main(args + ["--out", str(tmp_path / "b")]) == 0
    assert "reusing the adapter" in capsys.readouterr().out and not (tmp_path / "b" / "train").exists()
    # rejection sampling with another checker (reach_1m: ~5% of the prior's rooms pass), then with its own
    assert main(args + ["--out", str(tmp_path / "c"), "--task", "reach_1m", "--only-satisfying",
                        "--max-draws", "100"]) == 0
    scenes = load_layouts(tmp_path / "c" / "scenes.json", "bedroom")
    assert len(scenes) == 4 and task_results("reach_1m", scenes).all()
    assert "holds only scenes that pass the reach_1m checker" in (tmp_path / "c" / "report.md").read_text()
    capsys.readouterr()
    # nothing passes (study_zone: ~5% of the rooms, 4 floor plans, 1 draw each): one clear error, nothing written
    assert main(args + ["--out", str(tmp_path / "d"), "--task", "study_zone", "--only-satisfying",
                        "--max-draws", "1"]) == 2
    assert "no scene passed study_zone in 1 draws" in capsys.readouterr().err
    assert not (tmp_path / "d" / "scenes.json").exists()
    # a shipped adapter for the paper task's prompt is used at once, with an empty library
    from experiments.commands.generate import library_dir

    shutil.copytree(library_dir("bedroom", PROMPT), tmp_path / "shipped" / "two_nightstands")
    monkeypatch.setenv("IARCS_HOME", str(tmp_path / "empty_home"))
    assert main(args + ["--out", str(tmp_path / "e")]) == 0
    assert "using the adapter shipped for this paper task" in capsys.readouterr().out
    assert not (tmp_path / "e" / "train").exists() and (tmp_path / "e" / "scenes.json").exists()


def test_the_demo_runs_end_to_end_on_a_tiny_budget(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--task", "reach_1m", "--epochs", "1", "--num-scenes", "4"]) == 0
    report = (out / "report.md").read_text()
    for row in ("| prior |", "| stage 1 |", "| stage 2 |"):
        assert row in report
    assert "def reward(scene)" in report and "## Reflections" in report
    assert all((out / f"renders_{i}.png").exists() for i in range(3))
    from iarcs_env.viewer import BUNDLE

    if not BUNDLE.is_file():  # the viewer not built (no npm): the report says so
        assert "No 3D viewer: the 3D viewer is not built" in report
        return
    assert "[viewer.html](viewer.html)" in report
    page = (out / "viewer.html").read_text()
    rooms = json.loads(page.split('id="iarcs-rooms">', 1)[1].split("</script>", 1)[0])
    assert [r["name"] for r in rooms] == [f"{row} {j}" for row in ("prior", "stage 1", "stage 2") for j in range(4)]


def test_a_task_run_with_an_llm_agent_over_litellm_survives_a_failing_reflection(tiny_task_config, tmp_path):
    """The real litellm path inside training: synthesis and a reflection answered by a loopback server,
    then a reflection whose server keeps failing (training goes on with the last good reward)."""
    from test_llm_agent import FakeLLMServer

    server = FakeLLMServer()
    server.push({"fixture": "two_nightstands"}, {"fixture": "reflect_curriculum"}, {"status": 500}, {"status": 500})
    cfg = yaml.safe_load(tiny_task_config.read_text())
    cfg["task"].update(model="openai/test-model", api_base=server.url,
                       llm={"api_key": "test", "timeout": 5.0, "max_retries": 1, "backoff_base": 0.01})
    tiny_task_config.write_text(yaml.safe_dump(cfg))
    assert main(["train", "--config", str(tiny_task_config)]) == 0
    run = tmp_path / "run"
    entries = json.loads((run / "reward_memory.json").read_text())["entries"]
    assert entries[0]["proposal"]["source"] == "openai/test-model"
    assert [(e["kind"], e["epoch"], e["accepted"]) for e in entries] == [
        ("synthesize", 0, True), ("reflect", 2, True), ("reflect", 4, False)]
    assert "agent failed" in entries[2]["message"]
    assert entries[1]["proposal"]["curriculum"]  # the recorded reflection answer carries a curriculum
    usage = json.loads((run / "reward" / "llm_usage.json").read_text())
    assert usage["calls"] >= 2 and usage["prompt_tokens"] > 0 and usage["errors"] == 1
    assert any((run / "llm_cache").iterdir())
    assert (run / "reward" / "program.py").read_text() == entries[1]["proposal"]["code"]


def test_generate_only_satisfying_needs_a_checker(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("IARCS_HOME", str(tmp_path / "home"))
    assert main(["generate", "--constraint", "A bedroom with a reading corner", "--only-satisfying",
                 "--out", str(tmp_path / "g")]) == 2
    assert "--only-satisfying needs a task checker" in capsys.readouterr().err
    assert main(["generate", "--room", "livingroom", "--constraint", PROMPT, "--task", "two_nightstands",
                 "--out", str(tmp_path / "g")]) == 2
    assert "two_nightstands is a bedroom task but --room is livingroom" in capsys.readouterr().err
    assert not (tmp_path / "home").exists()  # refused before any training


def test_the_adapter_library_keys_adapters_by_the_weights_they_were_trained_on(tmp_path, monkeypatch):
    """A new shipped prior (or stage-1 adapter) must not reuse an adapter trained on the old one."""
    from agents.denoiser import ScenePrior
    from experiments.commands.generate import library_dir

    monkeypatch.setenv("IARCS_HOME", str(tmp_path / "home"))
    before = library_dir("bedroom", PROMPT)
    assert library_dir("bedroom", "  " + PROMPT.upper()) == before  # case and spacing do not matter
    prior = tmp_path / "other_prior.pt"
    prior.write_bytes(b"other weights")
    monkeypatch.setattr(ScenePrior, "default_path", staticmethod(lambda room: prior))
    after = library_dir("bedroom", PROMPT)
    assert after != before and after.name.split("-")[0] == before.name.split("-")[0]  # same slug, new hash
