"""The LLM reward agent (paper section 3.4, appendix E): constraint -> reasoning -> measurable checks ->
reward program ``def reward(scene)`` with a weight, validated in the sandbox, and revised by reflection.

    agent = make_agent("gemini/gemini-2.5-pro", cache_dir="runs/llm_cache")   # or make_agent() offline
    proposal = agent.synthesize("bedroom", "A bedroom with 2 night tables on either side of the bed")
    revised = agent.reflect(context)                                          # a ReflectionContext

The model answers in sections (REASONING / DECOMPOSITION / CODE / WEIGHT, optional NOT UNDERSTOOD,
NOTES and CURRICULUM). Every answer is parsed and checked: static checks (:func:`rewards.program_check.check_program`)
and a smoke test on fixture scenes (``RewardSandbox.load``). A failure goes back to the model as the next
user message, up to ``max_attempts`` answers; then :class:`RewardSynthesisError` carries every attempt.
Model call failures are :class:`rewards.llm.LLMError` (raised as they are).
"""

from __future__ import annotations

import base64
import json
import math
import re
import time
from dataclasses import dataclass

from .llm import LLMClient, LLMConfig, LLMError
from .proposal import ReflectionContext, RewardAgentProtocol, RewardProposal

__all__ = ["Attempt", "LLMRewardAgent", "ParsedAnswer", "RewardAgent", "RewardProposal", "RewardSynthesisError",
           "build_system_prompt", "make_agent", "parse_answer", "LLMError"]

RewardAgent = RewardAgentProtocol
"""What both the LLM agent and the offline planner implement."""

SYSTEM_PROMPT = """\
You are a reward engineer for a 3D indoor-scene generator. A diffusion model places furniture in rooms \
(each object: class, centre position, size, yaw); it is fine-tuned with reinforcement learning so that its \
scenes satisfy a user's natural-language constraint. Your reward program scores generated scenes for that \
constraint. It is added, with the weight you choose, to four universal rewards that are always on: \
collision (objects must not overlap), boundary (objects inside the floor plan), accessibility (free \
walkable floor) and object count (a plausible number of objects). Each universal reward is of order 1.

Work in three steps:
1. REASONING: what the constraint means physically in this room type: which objects, which spatial \
relations, which distances/angles/heights, and which typical human-scale dimensions apply \
(e.g. a wheelchair needs 0.9 m wide paths and a 1.5 m turning circle).
2. DECOMPOSITION: a list of measurable checks, each one expressible with the scene API below \
(counts, distances, gaps, offsets in an object's frame, facing/viewing angles, heights, wall distances, \
reachability, free circles). If part of the constraint cannot be measured with this API, say so under \
NOT UNDERSTOOD instead of guessing.
3. CODE: one Python function `def reward(scene):` returning a float tensor of shape (B,), one value per \
scene, higher is better, roughly in [0, 1]. Make it dense: give partial credit that grows as a scene gets \
closer to satisfying each check (use scene.below / scene.above / scene.within for smooth shaping), and \
combine the checks (e.g. a product or mean); a scene that lacks the required objects should get a low, \
finite value (never NaN). Put every threshold in a module-level UPPER_CASE constant (e.g. \
MAX_TOP_HEIGHT = 1.0) so that it can be relaxed or tightened later.
Then WEIGHT: one number, how strongly the task reward counts next to the universal rewards (usually 1 to 3).

Rules for the code: it runs in a sandbox on batches of scenes. Only `import math` and `import torch` are \
allowed (both are already available as globals); no other imports, no file or network access, no \
open/eval/exec/getattr/globals, no names or attributes starting with an underscore. Use only the scene API \
below; work on whole tensors (no Python loops over scenes or objects are needed). Class and group names \
must be ones listed below.

Scene API:
{api}

Answer in exactly this format:
REASONING:
<your reasoning>
DECOMPOSITION:
- <check 1>
- <check 2>
NOT UNDERSTOOD:
<parts of the constraint you could not turn into checks, or "none">
CODE:
```python
<module-level constants>

def reward(scene):
    ...
```
WEIGHT: <number>
"""

REFLECTION_FORMAT = """\
Revise the reward program from this training feedback (Eureka-style reward reflection):
- If task success stays low and flat, the reward is too hard or not informative: relax a threshold \
(a curriculum that starts easier and is tightened over later reflections) or simplify/densify the hardest term.
- If a reward component barely changes (max close to min), it gives no learning signal: rescale or rewrite it.
- If task success is high, tighten relaxed thresholds towards the user's real target.
- If the sandbox reported errors or NaN values, fix the code.
- Keep what works; change one thing at a time when you can.
Answer in the same format (REASONING, DECOMPOSITION, NOT UNDERSTOOD, CODE, WEIGHT), then add
NOTES:
<what you changed and why>
CURRICULUM:
<optional JSON {{"parameter": "UPPER_CASE_CONSTANT", "values": [easy, ..., final], "stage": {stage}}}, or "none">
"""

SECTIONS = ("REASONING", "DECOMPOSITION", "NOT UNDERSTOOD", "CODE", "WEIGHT", "NOTES", "CURRICULUM")
_HEADING = re.compile(
    r"^[ \t]*(?:#{1,6}[ \t]*)?(?:\*\*|__)?[ \t]*(?:\d+[.)][ \t]*)?"
    r"(REASONING|DECOMPOSITION|NOT[ _]UNDERSTOOD|CODE|WEIGHT|NOTES|CURRICULUM)"
    r"[ \t]*(?:\*\*|__)?[ \t]*(?::|$)[ \t]*(?:\*\*|__)?",
    re.IGNORECASE | re.MULTILINE)
_FENCE = re.compile(r"```[ \t]*([\w+-]*)[^\n]*\n(.*?)(?:```|\Z)", re.DOTALL)
_NONE_WORDS = {"", "none", "n/a", "na", "nothing", "-", "none.", "null", "{}"}


def build_system_prompt() -> str:
    """The system prompt, with the scene API generated from :mod:`rewards.scene_api`."""
    from .scene_api import api_reference  # lazy: pulls in torch and the geometry code

    return SYSTEM_PROMPT.format(api=api_reference())


# ---------------------------------------------------------------------------------------------- parsing


@dataclass
class ParsedAnswer:
    """The sections of one model answer; ``problems`` lists what is missing or malformed."""

    reasoning: str
    decomposition: list[str]
    code: str
    weight: float
    not_understood: list[str]
    notes: str
    curriculum: dict
    problems: list[str]


def parse_answer(text: str) -> ParsedAnswer:
    """Split an answer into its sections. Tolerates markdown headings, bold and numbering; code may come
    in any fenced block that defines ``reward`` (preferably under CODE)."""
    fences: list[tuple[str, str]] = []  # (language, body) of each fenced block, replaced by a marker

    def stash(m: re.Match) -> str:
        fences.append((m.group(1).lower(), m.group(2)))
        return f"\x00FENCE{len(fences) - 1}\x00"

    masked = _FENCE.sub(stash, text)
    sections: dict[str, str] = {}
    marks = list(_HEADING.finditer(masked))
    for k, m in enumerate(marks):
        name = m.group(1).upper().replace("_", " ")
        end = marks[k + 1].start() if k + 1 < len(marks) else len(masked)
        sections.setdefault(name, masked[m.end():end].strip())

    def unmask(s: str) -> str:
        return re.sub(r"\x00FENCE(\d+)\x00", lambda m: "```\n" + fences[int(m.group(1))][1] + "```", s)

    def fence_in(name: str) -> str | None:
        found = re.search(r"\x00FENCE(\d+)\x00", sections.get(name, ""))
        return fences[int(found.group(1))][1] if found else None

    problems: list[str] = []
    code = fence_in("CODE")
    if code is None or "def reward" not in code:
        candidates = [body for lang, body in fences if "def reward" in body]
        code = candidates[-1] if candidates else None
    if code is None and "def reward" in sections.get("CODE", ""):
        code = sections["CODE"]  # unfenced code under CODE:
    if code is None:
        problems.append("the answer has no ```python code block defining `def reward(scene):` under CODE:")
        code = ""
    code = code.strip("\n") + ("\n" if code.strip() else "")

    weight = 1.0
    raw_weight = sections.get("WEIGHT", "")
    number = re.search(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?", raw_weight)
    if number is None:
        problems.append("WEIGHT: is missing or has no number (give one number, e.g. WEIGHT: 2.0)")
    else:
        weight = float(number.group(0))
        if not math.isfinite(weight) or weight <= 0 or weight > 100:
            problems.append(f"WEIGHT: {number.group(0)} is not a usable weight (give a positive number, "
                            f"usually 1 to 3)")
            weight = 1.0

    curriculum: dict = {}
    raw_curriculum = (fence_in("CURRICULUM") or sections.get("CURRICULUM", "")).strip()
    if raw_curriculum.lower() not in _NONE_WORDS:
        start, end = raw_curriculum.find("{"), raw_curriculum.rfind("}")
        try:
            curriculum = json.loads(raw_curriculum[start:end + 1]) if start >= 0 else None
            if not isinstance(curriculum, dict):
                raise ValueError("not a JSON object")
            if "values" in curriculum and not isinstance(curriculum["values"], list):
                raise ValueError('"values" must be a list')
        except ValueError as exc:
            problems.append(f"CURRICULUM: is not a JSON object like {{\"parameter\": \"NAME\", \"values\": "
                            f"[...], \"stage\": 0}} ({exc}); write valid JSON or 'none'")
            curriculum = {}
        if curriculum.get("parameter") and code and not re.search(
                rf"^{re.escape(str(curriculum['parameter']))}\s*=", code, re.MULTILINE):
            problems.append(f"CURRICULUM: parameter {curriculum['parameter']!r} is not a module-level constant "
                            f"assigned in the code")

    return ParsedAnswer(
        reasoning=unmask(sections.get("REASONING", "")).strip(),
        decomposition=_items(unmask(sections.get("DECOMPOSITION", ""))),
        code=code,
        weight=weight,
        not_understood=_items(unmask(sections.get("NOT UNDERSTOOD", ""))),
        notes=unmask(sections.get("NOTES", "")).strip(),
        curriculum=curriculum,
        problems=problems,
    )


def _items(block: str) -> list[str]:
    """Bullet or numbered items of a section (plain lines when there are no bullets); [] for 'none'."""
    lines = [ln.strip() for ln in block.splitlines() if ln.strip()]
    bullet = re.compile(r"^(?:[-*+\u2022]|\d+[.)])\s+")
    if any(bullet.match(ln) for ln in lines):
        items: list[str] = []
        for ln in lines:
            if bullet.match(ln):
                items.append(bullet.sub("", ln))
            elif items:  # continuation line of the previous item
                items[-1] = items[-1] + " " + ln
        lines = items
    return [ln for ln in lines if ln.lower().strip(" .") not in _NONE_WORDS]


# ----------------------------------------------------------------------------------------------- agent


@dataclass
class Attempt:
    """One model answer and why it was rejected ("" when accepted)."""

    answer: str
    problem: str


class RewardSynthesisError(RuntimeError):
    """The model gave no valid reward program within ``max_attempts`` answers; ``attempts`` has them all."""

    def __init__(self, message: str, attempts: list[Attempt]):
        super().__init__(message)
        self.attempts = attempts


class LLMRewardAgent:
    """Reward synthesis and reflection with an LLM, validated through the sandbox.

    ``sandbox``: a :class:`rewards.sandbox.RewardSandbox` for the smoke test; when None the agent starts
    its own for the room on first use (and closes it in :meth:`close`)."""

    def __init__(self, client: LLMClient, sandbox=None, max_attempts: int = 3):
        if max_attempts < 1:
            raise ValueError("max_attempts must be at least 1")
        self.client = client
        self.sandbox = sandbox
        self.max_attempts = max_attempts
        self._own_sandbox = None
        self._system: str | None = None

    # -- protocol

    def synthesize(self, room: str, constraint: str, feedback: str | None = None) -> RewardProposal:
        """A validated reward program for ``constraint``; ``feedback`` is an error from a previous program."""
        text = f"Room type: {room}.\n{_room_classes(room)}\nConstraint: \"{constraint}\"\n"
        if feedback:
            text += (f"\nA previous reward program for this constraint failed when it was used:\n{feedback}\n"
                     f"Write a corrected program.\n")
        text += "\nAnswer in the required format (REASONING, DECOMPOSITION, NOT UNDERSTOOD, CODE, WEIGHT)."
        return self._converse(room, constraint, [{"role": "user", "content": text}], notes="")

    def reflect(self, context: ReflectionContext) -> RewardProposal:
        """A revised program from training feedback (statistics, history, renders when the model sees images)."""
        p = context.proposal
        parts = [f"Room type: {p.room}.", _room_classes(p.room), f"Constraint: \"{p.constraint}\"", "",
                 "The reward program in use:", _describe(p), "", "Training feedback:", context.summary()]
        if context.history:
            parts += ["", "Earlier programs and what happened with them, oldest first:"]
            for k, item in enumerate(context.history[-5:], 1):
                parts.append(_describe_history(k, item))
        parts += ["", REFLECTION_FORMAT.format(stage=context.stage)]
        text = "\n".join(parts)
        if context.images and self.client.supports_vision:
            content: list[dict] | str = [{"type": "text", "text": text + "\nTop-down renders of recent samples "
                                          "(one image per grid of scenes) follow."}]
            for png in context.images:
                url = "data:image/png;base64," + base64.b64encode(png).decode()
                content.append({"type": "image_url", "image_url": {"url": url}})
        else:
            if context.images:
                text += (f"\n({len(context.images)} top-down render(s) omitted: {self.client.model} does not "
                         f"accept images.)")
            content = text
        return self._converse(p.room, p.constraint, [{"role": "user", "content": content}],
                              notes=f"reflection stage {context.stage}", base=p)

    # -- the validation loop

    def _converse(self, room: str, constraint: str, messages: list[dict], notes: str,
                  base: RewardProposal | None = None) -> RewardProposal:
        if self._system is None:
            self._system = build_system_prompt()
        messages = [{"role": "system", "content": self._system}] + messages
        attempts: list[Attempt] = []
        deadline = time.monotonic() + self.client.config.max_seconds
        for _ in range(self.max_attempts):
            reply = self.client.complete(messages, deadline=deadline)
            parsed = parse_answer(reply.text)
            problem = self._validate(room, parsed)
            attempts.append(Attempt(reply.text, problem))
            if not problem:
                return self._proposal(room, constraint, parsed, notes, attempts, base)
            messages = messages + [
                {"role": "assistant", "content": reply.text},
                {"role": "user", "content": f"Your answer was rejected:\n{problem}\n\nFix this and answer again "
                                            f"in the full format (REASONING, DECOMPOSITION, NOT UNDERSTOOD, "
                                            f"CODE, WEIGHT{', NOTES, CURRICULUM' if base else ''})."},
            ]
        summary = "\n".join(f"  attempt {k}: " + "\n    ".join(line.lstrip("- ") for line in a.problem.splitlines()[:4])
                            for k, a in enumerate(attempts, 1))  # (the reason, not only its headline)
        raise RewardSynthesisError(
            f"{self.client.model} gave no valid reward program for {constraint!r} in {len(attempts)} attempt(s):\n"
            f"{summary}\nThe last answer and every problem are in .attempts; try another model, raise "
            f"max_attempts, or use the offline planner.", attempts)

    def _validate(self, room: str, parsed: ParsedAnswer) -> str:
        """'' when the answer is usable, else the message that goes back to the model."""
        if parsed.problems:
            return "\n".join(f"- {p}" for p in parsed.problems)
        from .program_check import check_program

        issues = check_program(parsed.code)
        if issues:
            return "The program failed the static checks:\n" + "\n".join(f"- {i}" for i in issues)
        result = self._sandbox(room).load(parsed.code)
        if not result.ok:
            said = "smoke test" in result.message
            return result.message if said else f"The program failed the smoke test on fixture scenes:\n{result.message}"
        return ""

    def _sandbox(self, room: str):
        if self.sandbox is not None:
            return self.sandbox
        if self._own_sandbox is None or self._own_sandbox[0] != room:
            from .sandbox import RewardSandbox

            self.close()
            self._own_sandbox = (room, RewardSandbox(room=room))
        return self._own_sandbox[1]

    def _proposal(self, room, constraint, parsed: ParsedAnswer, notes: str, attempts: list[Attempt],
                  base: RewardProposal | None) -> RewardProposal:
        extra = f"accepted on attempt {len(attempts)} of {self.max_attempts}" if len(attempts) > 1 else ""
        text = "; ".join(s for s in (notes, parsed.notes, extra) if s)
        return RewardProposal(constraint=constraint, reasoning=parsed.reasoning,
                              decomposition=parsed.decomposition, code=parsed.code, weight=parsed.weight, room=room,
                              source=self.client.model, not_understood=parsed.not_understood,
                              curriculum=parsed.curriculum, notes=text)

    def close(self) -> None:
        """Stop the sandbox this agent started (not one it was given)."""
        if self._own_sandbox is not None:
            self._own_sandbox[1].close()
            self._own_sandbox = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _room_classes(room: str) -> str:
    from iarcs_env.rooms import get_room

    return f"Object classes that occur in this room type: {', '.join(get_room(room).classes)}."


def _describe(p: RewardProposal) -> str:
    checks = "\n".join(f"- {c}" for c in p.decomposition) or "- (none listed)"
    extra = f"\nCurriculum: {json.dumps(p.curriculum)}" if p.curriculum else ""
    return (f"DECOMPOSITION:\n{checks}\nCODE:\n```python\n{p.code.rstrip()}\n```\nWEIGHT: {p.weight:g}{extra}"
            + (f"\nNotes: {p.notes}" if p.notes else ""))


def _describe_history(k: int, item: dict) -> str:
    prop = item.get("proposal") or {}
    outcome = json.dumps(item.get("outcome") or {}, default=str)
    if len(outcome) > 800:
        outcome = outcome[:800] + "..."
    code = (prop.get("code") or "").rstrip()
    notes = f"\nNotes: {prop['notes']}" if prop.get("notes") else ""
    return f"Program {k} (weight {prop.get('weight', 1.0)}):\n```python\n{code}\n```{notes}\nOutcome: {outcome}"


# ------------------------------------------------------------------------------------------------ factory


def make_agent(model: str | dict | LLMConfig | None = None, api_base: str | None = None, sandbox=None,
               max_attempts: int = 3, **llm_kwargs):
    """The LLM agent when a model is given (a name, an llm config dict or an LLMConfig), else the offline
    planner. ``llm_kwargs`` are :class:`rewards.llm.LLMConfig` fields (timeout, cache_dir, ...)."""
    if model is None or model == "" or model == "offline":
        from .planner import OfflinePlanner

        return OfflinePlanner()
    if isinstance(model, LLMConfig):
        config = model
    elif isinstance(model, dict):
        config = LLMConfig.from_dict({**model, **({"api_base": api_base} if api_base else {}), **llm_kwargs})
    else:
        config = LLMConfig.from_dict({"model": model, "api_base": api_base, **llm_kwargs})
    return LLMRewardAgent(LLMClient(config), sandbox=sandbox, max_attempts=max_attempts)
