"""The LLM reward agent through the real litellm path, against a loopback OpenAI-compatible server that
replays recorded answers (tests/fixtures/llm/*.json) and failure behaviours (429, 500, slow answers)."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import pytest

from experiments.llm_replay import ReplayServer
from rewards.agent import LLMRewardAgent, RewardSynthesisError, make_agent, parse_answer
from rewards.llm import (LLMAuthError, LLMBadRequestError, LLMClient, LLMConfig, LLMConfigError,
                         LLMConnectionError, LLMRateLimitError, LLMServerError, LLMTimeoutError, load_litellm)
from rewards.proposal import ReflectionContext, RewardProposal

FIXTURES = Path(__file__).parent / "fixtures" / "llm"
TASKS = ["reach_1m", "tv_from_bed", "study_zone", "two_nightstands", "wheelchair"]


def recorded(name: str) -> dict:
    return json.loads((FIXTURES / f"{name}.json").read_text())


def content_of(name: str) -> str:
    return recorded(name)["response"]["choices"][0]["message"]["content"]


# ------------------------------------------------------------------------------------- loopback server


class FakeLLMServer(ReplayServer):
    """POST /v1/chat/completions answers from a queue of behaviours:
    ``{"fixture": name}``, ``{"content": text}``, ``{"status": 429}``, optionally with ``"sleep": seconds``."""

    def __init__(self):
        self.queue: list[dict] = []
        self.requests: list[dict] = []
        super().__init__(answers={})

    def answer(self, body: dict, headers) -> tuple[int, dict]:
        self.requests.append({"body": body, "auth": headers.get("Authorization")})
        step = self.queue.pop(0) if self.queue else {"status": 500, "message": "no answer queued"}
        time.sleep(step.get("sleep", 0))
        return self.payload(step, body)

    @staticmethod
    def payload(step: dict, body: dict) -> tuple[int, dict]:
        status = step.get("status", 200)
        if status != 200:
            return status, {"error": {"message": step.get("message", f"recorded error {status}"),
                                      "type": "server_error", "code": status}}
        if "fixture" in step:
            response = dict(recorded(step["fixture"])["response"])
        else:
            response = {"id": "chatcmpl-x", "object": "chat.completion", "created": 1760000000,
                        "choices": [{"index": 0, "message": {"role": "assistant", "content": step.get("content", "")},
                                     "finish_reason": "stop"}],
                        "usage": {"prompt_tokens": 100, "completion_tokens": 20, "total_tokens": 120}}
        response["model"] = body["model"]
        return 200, response

    def push(self, *steps: dict) -> None:
        self.queue.extend(steps)

    def messages(self, k: int) -> list[dict]:
        """The chat messages of the k-th request."""
        return self.requests[k]["body"]["messages"]


@pytest.fixture
def server():
    srv = FakeLLMServer()
    yield srv
    srv.close()


def make_client(server, model="openai/test-model", **kw) -> LLMClient:
    cfg = dict(model=model, api_base=server.url, api_key="test", timeout=3.0, max_retries=2, backoff_base=0.01,
               backoff_max=0.05)
    cfg.update(kw)
    return LLMClient(LLMConfig(**cfg))


@pytest.fixture(scope="module")
def sandbox():
    from rewards.sandbox import RewardSandbox

    with RewardSandbox(room="bedroom") as box:
        yield box


def make(server, sandbox, max_attempts=3, **kw) -> LLMRewardAgent:
    return LLMRewardAgent(make_client(server, **kw), sandbox=sandbox, max_attempts=max_attempts)


# --------------------------------------------------------------------------------------------- synthesis


EXPECTED_WEIGHTS = {"reach_1m": 2.0, "tv_from_bed": 2.0, "study_zone": 1.5, "two_nightstands": 2.0,
                    "wheelchair": 2.5}


@pytest.mark.parametrize("task", TASKS)
def test_good_answer_for_each_task(server, sandbox, task):
    server.push({"fixture": task})
    rec = recorded(task)
    proposal = make(server, sandbox).synthesize("bedroom", rec["constraint"])
    assert isinstance(proposal, RewardProposal)
    assert proposal.constraint == rec["constraint"] and proposal.room == "bedroom"
    assert proposal.source == "openai/test-model"
    assert len(proposal.reasoning) > 50
    assert len(proposal.decomposition) >= 3 and all(proposal.decomposition)
    assert "def reward(scene):" in proposal.code and "```" not in proposal.code
    assert proposal.weight == EXPECTED_WEIGHTS[task]
    assert len(server.requests) == 1
    system, user = server.messages(0)
    assert system["role"] == "system" and "scene.local_offset()" in system["content"]
    assert "REASONING" in system["content"] and "WEIGHT" in system["content"]
    assert rec["constraint"] in user["content"] and "nightstand" in user["content"]


def test_not_understood_is_kept(server, sandbox):
    server.push({"fixture": "tv_from_bed"})
    proposal = make(server, sandbox).synthesize("bedroom", recorded("tv_from_bed")["constraint"])
    assert proposal.not_understood == ["the 4K resolution itself (only the viewing distance it implies is measured)"]


def test_syntax_error_then_good(server, sandbox):
    from rewards.sandbox import check_program

    bad = parse_answer(content_of("syntax_error")).code
    issues = check_program(bad)
    assert issues
    server.push({"fixture": "syntax_error"}, {"fixture": "two_nightstands"})
    agent = make(server, sandbox)
    proposal = agent.synthesize("bedroom", "A bedroom with 2 night tables on either side of the bed")
    assert proposal.weight == 2.0 and "accepted on attempt 2" in proposal.notes
    assert len(server.requests) == 2
    follow = server.messages(1)
    assert follow[-2] == {"role": "assistant", "content": content_of("syntax_error")}
    assert follow[-1]["role"] == "user" and "static checks" in follow[-1]["content"]
    assert all(issue in follow[-1]["content"] for issue in issues)


def test_forbidden_import_then_good(server, sandbox):
    server.push({"fixture": "forbidden_import"}, {"fixture": "reach_1m"})
    proposal = make(server, sandbox).synthesize("bedroom", recorded("reach_1m")["constraint"])
    assert "MAX_TOP_HEIGHT" in proposal.code
    assert "os" in server.messages(1)[-1]["content"]


@pytest.mark.parametrize("bad, hint", [("wrong_shape", "shape"), ("raises", "television")])
def test_smoke_test_failure_then_good(server, sandbox, bad, hint):
    server.push({"fixture": bad}, {"fixture": "tv_from_bed"})
    proposal = make(server, sandbox).synthesize("bedroom", recorded("tv_from_bed")["constraint"])
    assert "MAX_ANGLE_DEG" in proposal.code
    follow = server.messages(1)[-1]["content"]
    assert "smoke test" in follow and hint in follow


def test_no_code_gives_up_after_max_attempts(server, sandbox):
    server.push(*[{"fixture": "no_code"}] * 3)
    agent = make(server, sandbox, max_attempts=3)
    with pytest.raises(RewardSynthesisError) as err:
        agent.synthesize("bedroom", "A wheelchair-accessible bedroom")
    assert len(server.requests) == 3 and len(err.value.attempts) == 3
    assert all("no ```python code block" in a.problem for a in err.value.attempts)
    text = str(err.value)
    assert "no valid reward program" in text and "3 attempt" in text and "wheelchair" in text
    assert "no ```python code block" in server.messages(2)[-1]["content"]


def test_feedback_is_sent(server, sandbox):
    server.push({"fixture": "wheelchair"})
    make(server, sandbox).synthesize("bedroom", "A wheelchair-accessible bedroom",
                                     feedback="ValueError: NaN in reward at batch 3")
    assert "NaN in reward at batch 3" in server.messages(0)[-1]["content"]


# ------------------------------------------------------------------------------------ transport failures


def test_rate_limit_then_success(server):
    server.push({"status": 429}, {"content": "hello"})
    client = make_client(server)
    reply = client.complete([{"role": "user", "content": "hi"}])
    assert reply.text == "hello" and reply.attempts == 2 and not reply.cached
    assert client.usage.retries == 1 and client.usage.requests == 2 and client.usage.backoff_seconds > 0


def test_rate_limit_gives_up(server):
    server.push(*[{"status": 429}] * 3)
    client = make_client(server, max_retries=2)
    with pytest.raises(LLMRateLimitError, match="rate limited .* after 2 retries") as err:
        client.complete([{"role": "user", "content": "hi"}])
    assert err.value.attempts == 3 and client.usage.errors == 1 and client.usage.calls == 0


def test_server_error_then_success(server):
    server.push({"status": 500}, {"status": 503}, {"content": "ok"})
    client = make_client(server)
    assert client.complete([{"role": "user", "content": "hi"}]).text == "ok"
    assert client.usage.retries == 2


def test_server_error_gives_up(server):
    server.push(*[{"status": 500, "message": "model crashed"}] * 2)
    with pytest.raises(LLMServerError, match="kept failing .*model crashed"):
        make_client(server, max_retries=1).complete([{"role": "user", "content": "hi"}])


@pytest.mark.parametrize("status, error", [(401, LLMAuthError), (400, LLMBadRequestError),
                                           (404, LLMBadRequestError)])
def test_no_retry_on_client_errors(server, status, error):
    server.push({"status": status, "message": "nope"}, {"content": "never sent"})
    with pytest.raises(error):
        make_client(server).complete([{"role": "user", "content": "hi"}])
    assert len(server.requests) == 1


def test_timeout_then_success(server):
    server.push({"sleep": 2.0, "content": "late"}, {"content": "on time"})
    client = make_client(server, timeout=1.0)  # generous for the on-time answer on a busy machine
    assert client.complete([{"role": "user", "content": "hi"}]).text == "on time"
    assert client.usage.retries == 1


def test_timeout_gives_up(server):
    server.push({"sleep": 1.5, "content": "late"}, {"sleep": 1.5, "content": "late"})
    client = make_client(server, timeout=0.5, max_retries=1)
    with pytest.raises(LLMTimeoutError, match=r"timeout of 0.5 s \(2 attempts\)"):
        client.complete([{"role": "user", "content": "hi"}])


def test_a_hanging_server_costs_at_most_max_seconds(server, sandbox):
    """A server that never answers in time: the whole synthesis (every attempt, retry and back-off) stops at
    max_seconds with a message naming the server and the setting, instead of timeout x retries x attempts."""
    server.push({"content": "warm"}, *[{"sleep": 3.0, "content": "late"}] * 12)
    agent = make(server, sandbox, max_attempts=3, timeout=2.0, max_retries=4, max_seconds=2.5)
    agent.client.complete([{"role": "user", "content": "warm up"}])  # (litellm's one-off start is not the server's)
    t0 = time.monotonic()
    with pytest.raises(LLMTimeoutError, match=r"no usable answer within max_seconds = 2.5 s .*--max-seconds"):
        agent.synthesize("bedroom", "A bedroom with a desk")
    assert time.monotonic() - t0 < 4.0  # (without the limit: 3 attempts x 5 requests x 2 s = 30 s)


def test_the_reason_a_program_was_rejected_is_shown(server, sandbox):
    server.push(*[{"fixture": "forbidden_import"}] * 2)
    with pytest.raises(RewardSynthesisError) as err:
        make(server, sandbox, max_attempts=2).synthesize("bedroom", recorded("reach_1m")["constraint"])
    assert str(err.value).count("`import os` is not allowed") == 2  # each attempt's reason, not only "failed"


def test_connection_refused_names_api_base():
    with socket.socket() as s:  # a port that nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base = f"http://127.0.0.1:{port}/v1"
    client = LLMClient(LLMConfig(model="openai/test-model", api_base=base, api_key="test", timeout=1.0,
                                 max_retries=1, backoff_base=0.01))
    with pytest.raises(LLMConnectionError, match="could not reach the model server at " + base) as err:
        client.complete([{"role": "user", "content": "hi"}])
    assert err.value.attempts == 2 and "api_base" in str(err.value)


def test_missing_gemini_key_names_env_var_without_network(monkeypatch):
    litellm = load_litellm()
    for name in ("GEMINI_API_KEY", "GOOGLE_API_KEY"):
        monkeypatch.delenv(name, raising=False)

    def no_network(**kwargs):
        raise AssertionError("a request was sent")

    monkeypatch.setattr(litellm, "completion", no_network)
    client = LLMClient(LLMConfig(model="gemini/gemini-2.5-pro"))
    with pytest.raises(LLMConfigError, match="GEMINI_API_KEY"):
        client.complete([{"role": "user", "content": "hi"}])
    monkeypatch.delenv("IARCS_TEST_KEY", raising=False)
    with pytest.raises(LLMConfigError, match="IARCS_TEST_KEY"):
        LLMClient(LLMConfig(model="openai/x", api_key_env="IARCS_TEST_KEY")).complete([{"role": "user",
                                                                                          "content": "hi"}])


def test_key_from_env_var_is_sent(server, monkeypatch):
    monkeypatch.setenv("IARCS_TEST_KEY", "sekrit")
    server.push({"content": "ok"})
    make_client(server, api_key=None, api_key_env="IARCS_TEST_KEY").complete([{"role": "user", "content": "hi"}])
    assert server.requests[0]["auth"] == "Bearer sekrit"


def test_self_hosted_server_without_key(server, monkeypatch):
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    server.push({"content": "ok"})
    assert make_client(server, api_key=None).complete([{"role": "user", "content": "hi"}]).text == "ok"
    assert server.requests[0]["auth"] == "Bearer EMPTY"


# ------------------------------------------------------------------------------------- cache and usage


def test_cache_hit_on_repeated_prompt(server, tmp_path):
    server.push({"content": "first"}, {"content": "second"})
    messages = [{"role": "user", "content": "same prompt"}]
    client = make_client(server, cache_dir=str(tmp_path / "cache"))
    first = client.complete(messages)
    again = client.complete(messages)
    assert (first.text, first.cached) == ("first", False)
    assert (again.text, again.cached, again.cost, again.prompt_tokens) == ("first", True, 0.0, 0)
    assert len(server.requests) == 1
    assert client.usage.calls == 2 and client.usage.cache_hits == 1 and client.usage.prompt_tokens == 100
    files = list((tmp_path / "cache").iterdir())
    assert len(files) == 1 and files[0].name == client.cache_key(messages) + ".json"
    # a new client (a new run) reads the same cache; a different prompt or temperature misses
    other = make_client(server, cache_dir=str(tmp_path / "cache"))
    assert other.complete(messages).cached
    assert make_client(server, cache_dir=str(tmp_path / "cache"), temperature=0.9).cache_key(messages) \
        != client.cache_key(messages)
    assert other.complete([{"role": "user", "content": "new"}]).text == "second"


def test_token_and_cost_totals(server):
    litellm = load_litellm()
    server.push({"fixture": "reach_1m"}, {"fixture": "wheelchair"})
    client = make_client(server, model="openai/gpt-4o-mini")  # a model litellm has prices for
    replies = [client.complete([{"role": "user", "content": f"q{k}"}]) for k in range(2)]
    price = litellm.model_cost["gpt-4o-mini"]
    for reply, name in zip(replies, ["reach_1m", "wheelchair"]):
        usage = recorded(name)["response"]["usage"]
        assert (reply.prompt_tokens, reply.completion_tokens) == (usage["prompt_tokens"], usage["completion_tokens"])
        expected = usage["prompt_tokens"] * price["input_cost_per_token"] \
            + usage["completion_tokens"] * price["output_cost_per_token"]
        assert reply.cost == pytest.approx(expected)
    u = client.usage
    assert u.calls == 2 and u.requests == 2 and u.cache_hits == 0
    assert u.prompt_tokens == sum(r.prompt_tokens for r in replies)
    assert u.completion_tokens == sum(r.completion_tokens for r in replies)
    assert u.cost == pytest.approx(sum(r.cost for r in replies)) and u.cost > 0
    assert set(u.to_dict()) >= {"calls", "cache_hits", "prompt_tokens", "completion_tokens", "cost", "retries"}


def test_custom_prices_for_self_hosted_models(server):
    server.push({"content": "ok"})
    client = make_client(server, input_cost_per_token=1e-6, output_cost_per_token=2e-6)
    assert client.complete([{"role": "user", "content": "hi"}]).cost == pytest.approx(100e-6 + 40e-6)


# ------------------------------------------------------------------------------------------- reflection


def _context(images=()) -> ReflectionContext:
    p = RewardProposal(**{k: v for k, v in parse_answer(content_of("wheelchair")).__dict__.items()
                          if k in ("reasoning", "decomposition", "code", "weight", "not_understood")},
                       constraint="A wheelchair-accessible bedroom", source="openai/test-model")
    stats = {"task": {"values": [0.40, 0.41, 0.40], "max": 0.42, "mean": 0.40, "min": 0.39},
             "collision": {"values": [-0.2, -0.1, -0.1], "max": 0.0, "mean": -0.13, "min": -0.5}}
    history = [{"proposal": p.to_dict(), "outcome": {"task_success": 0.05, "epochs": 50}}]
    return ReflectionContext(p, stage=0, component_stats=stats, task_success=[0.05, 0.04, 0.05], history=history,
                             images=list(images), sandbox_messages=["2 NaN values clamped"])


def test_reflection_with_curriculum_text_only(server, sandbox):
    server.push({"fixture": "reflect_curriculum"})
    agent = make(server, sandbox)
    assert not agent.client.supports_vision
    revised = agent.reflect(_context(images=[b"\x89PNG fake"]))
    assert revised.curriculum == {"parameter": "AGENT_RADIUS", "values": [0.3, 0.375, 0.45], "stage": 0}
    assert "Relaxed AGENT_RADIUS" in revised.notes and "reflection stage 0" in revised.notes
    assert revised.weight == 3.0 and "AGENT_RADIUS = 0.3" in revised.code
    prompt = server.messages(0)[-1]["content"]
    assert isinstance(prompt, str)
    assert "Task success (independent checker)" in prompt and "2 NaN values clamped" in prompt
    assert "Earlier programs" in prompt and '"task_success": 0.05' in prompt
    assert "1 top-down render(s) omitted" in prompt and "CURRICULUM" in prompt


def test_reflection_sends_images_to_vision_models(server, sandbox):
    server.push({"fixture": "reflect_curriculum"})
    agent = make(server, sandbox, model="openai/gpt-4o")
    assert agent.client.supports_vision
    agent.reflect(_context(images=[b"\x89PNG one", b"\x89PNG two"]))
    content = server.messages(0)[-1]["content"]
    assert isinstance(content, list) and content[0]["type"] == "text"
    urls = [part["image_url"]["url"] for part in content[1:]]
    assert len(urls) == 2 and all(u.startswith("data:image/png;base64,") for u in urls)


def test_bad_curriculum_is_sent_back(server, sandbox):
    broken = content_of("reflect_curriculum").replace('"stage": 0}', '"stage": 0')
    server.push({"content": broken}, {"fixture": "reflect_curriculum"})
    revised = make(server, sandbox).reflect(_context())
    assert revised.curriculum["parameter"] == "AGENT_RADIUS"
    assert "CURRICULUM" in server.messages(1)[-1]["content"]


# ------------------------------------------------------------------------------------ parsing and config


def test_parse_markdown_variants():
    text = ("## 1. Reasoning\nBeds need space.\n\n**Decomposition:**\n1. bed exists\n2. gap to wall\n   >= 0.5 m\n"
            "**Not understood:** none\n### Code\nHere it is:\n```py\nLIMIT = 0.5\n\ndef reward(scene):\n"
            "    # CODE: comments with section words stay in the code\n    return scene.count('bed')\n```\n"
            "**Weight:** 1.25 (moderate)\n")
    p = parse_answer(text)
    assert p.problems == [] and p.reasoning == "Beds need space."
    assert p.decomposition == ["bed exists", "gap to wall >= 0.5 m"] and p.not_understood == []
    assert p.code.startswith("LIMIT = 0.5") and "# CODE: comments" in p.code and p.weight == 1.25


def test_parse_reports_missing_and_bad_parts():
    assert any("WEIGHT" in s for s in parse_answer("CODE:\n```python\ndef reward(scene):\n    return 1\n```").problems)
    assert any("not a usable weight" in s for s in parse_answer(
        "CODE:\n```python\ndef reward(scene):\n    return 1\n```\nWEIGHT: -2").problems)
    p = parse_answer("REASONING: x\nCODE:\n```python\nA = 1\ndef reward(scene):\n    return A\n```\nWEIGHT: 1\n"
                     "CURRICULUM: {\"parameter\": \"B\", \"values\": [1, 2]}")
    assert any("'B' is not a module-level constant" in s for s in p.problems)


def test_config_from_dict():
    cfg = LLMConfig.from_dict({"model": "gemini/gemini-2.5-pro", "timeout": 30, "cache_dir": "runs/c",
                               "api_key": "secret"})
    assert cfg.timeout == 30 and cfg.to_dict()["api_key"] == "***"
    with pytest.raises(ValueError, match="unknown llm config key.*tiemout.*valid keys"):
        LLMConfig.from_dict({"model": "x/y", "tiemout": 3})
    with pytest.raises(ValueError, match="needs a 'model'"):
        LLMConfig.from_dict({"timeout": 3})


def test_make_agent(server):
    agent = make_agent("openai/test-model", api_base=server.url, api_key="test", timeout=5, max_attempts=2)
    assert isinstance(agent, LLMRewardAgent) and agent.max_attempts == 2
    assert agent.client.config.api_base == server.url and agent.client.config.timeout == 5
    agent = make_agent({"model": "gemini/gemini-2.5-pro", "cache_dir": "x"})
    assert agent.client.config.cache_dir == "x"
    planner = pytest.importorskip("rewards.planner")
    assert isinstance(make_agent(), planner.OfflinePlanner)
