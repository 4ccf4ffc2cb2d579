"""experiments/llm_replay.py: the loopback server that answers the litellm agent from recorded answers, so that
stage 2 trains the recorded programs (issue 38) through the agent's real path."""

from __future__ import annotations

import json
import sys

import pytest

from experiments.llm_replay import RECORDED, ReplayServer, choose, load_answers, main
from rewards.agent import make_agent
from rewards.proposal import ReflectionContext

TASKS = ["reach_1m", "tv_from_bed", "study_zone", "two_nightstands", "wheelchair"]


def constraint_of(name: str) -> str:
    return json.loads((RECORDED / f"{name}.json").read_text())["constraint"]


def test_answers_are_the_tasks_files_and_the_marked_reflection_not_the_failure_behaviours():
    answers = load_answers(RECORDED)
    tasks = {entry["file"] for (_, reflecting), entry in answers.items() if not reflecting}
    assert tasks == {f"{t}.json" for t in TASKS}
    assert [entry["file"] for (_, reflecting), entry in answers.items() if reflecting] == ["reflect_curriculum.json"]


def test_a_request_gets_the_answer_for_the_constraint_it_quotes():
    answers = load_answers(RECORDED)
    ask = [{"role": "system", "content": "..."}, {"role": "user", "content": 'Room type: bedroom.\nConstraint: "%s"\n'}]

    def with_text(constraint, extra=""):
        return [ask[0], {"role": "user", "content": ask[1]["content"] % constraint + extra}]

    entry, kind = choose(answers, with_text(constraint_of("two_nightstands")))
    assert (entry["file"], kind) == ("two_nightstands.json", "synthesis")
    # a reflection: the recorded reflection where there is one, else the same program (the model keeps it)
    entry, kind = choose(answers, with_text(constraint_of("wheelchair"), "\nTraining feedback:\nsuccess 5%"))
    assert (entry["file"], kind) == ("reflect_curriculum.json", "reflection")
    entry, kind = choose(answers, with_text(constraint_of("two_nightstands"), "\nTraining feedback:\nsuccess 5%"))
    assert (entry["file"], kind) == ("two_nightstands.json", "reflection")
    entry, why = choose(answers, with_text("A kitchen with a fridge"))
    assert entry is None and "'A kitchen with a fridge'" in why and "A wheelchair-accessible bedroom" in why


@pytest.fixture(scope="module")
def served():
    server = ReplayServer(load_answers(RECORDED))
    agent = make_agent("openai/recorded", api_base=server.url, timeout=10.0, max_retries=0)
    yield server, agent
    agent.close()
    server.close()


def test_the_litellm_agent_writes_and_keeps_the_recorded_program_through_the_server(served):
    server, agent = served
    proposal = agent.synthesize("bedroom", constraint_of("two_nightstands"))
    recorded = json.loads((RECORDED / "two_nightstands.json").read_text())["response"]["choices"][0]["message"]
    assert proposal.source == "openai/recorded" and proposal.weight == 2.0
    assert proposal.code.strip() in recorded["content"]
    kept = agent.reflect(ReflectionContext(proposal=proposal, stage=1, component_stats={}, task_success=[0.3, 0.35]))
    assert kept.code == proposal.code
    assert [s["kind"] for s in server.served[-2:]] == ["synthesis", "reflection"]


def test_main_serves_while_the_command_runs_and_returns_its_status():
    assert main(["--port", "0", "--", sys.executable, "-c", "raise SystemExit(3)"]) == 3
