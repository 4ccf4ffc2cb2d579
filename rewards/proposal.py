"""What the reward-synthesis agent produces and what it reflects on (paper section 3.4, appendix E).

A :class:`RewardProposal` keeps the agent's three outputs for one natural-language constraint: its
reasoning, the decomposition into measurable checks, and the reward program (``def reward(scene)``, run
in the sandbox against :mod:`rewards.scene_api`) with the weight it gets next to the universal rewards.
A :class:`ReflectionContext` is what the agent sees every K training stages (Eureka-style statistics of
each reward component, task success, the previous programs and their outcomes, top-down renders).

Both serialise to plain JSON so the reward evolution memory (:mod:`rewards.memory`) can store them.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol


#: Words that change what a request means (negation, direction, quantifiers): a program that ignored one may reward
#: something else or the opposite of what was asked.
MEANING_WORDS = frozenset("""
not no never without none nothing neither nor except unless avoid cannot can't don't doesn't isn't aren't
toward towards away facing faces face behind beside either both between centred centered centre center middle
against opposite apart far near close closer nearer farther further beyond around inside outside
every each all any some least most more fewer less exactly only than maximum minimum max min
front left right corner or
""".split())


def meaning_lost(not_understood: list[str]) -> list[str]:
    """The not-understood parts of a request that hold a word changing its meaning (:data:`MEANING_WORDS`)."""
    return [part for part in not_understood
            if MEANING_WORDS & {w.strip("'") for w in re.findall(r"[a-z']+", part.lower().replace("’", "'"))}]


@dataclass
class RewardProposal:
    """One reward program for a constraint, with the reasoning and decomposition that led to it."""

    constraint: str
    """The user's natural-language constraint (the prompt)."""
    reasoning: str
    """The agent's reasoning (step 1)."""
    decomposition: list[str]
    """Measurable checks the constraint was decomposed into (step 2)."""
    code: str
    """Python source defining ``def reward(scene) -> tensor (B,)`` (step 3)."""
    weight: float = 1.0
    """Weight of the task reward next to the universal rewards."""
    room: str = "bedroom"
    source: str = "offline"
    """Who wrote it: ``offline`` (the planner) or the litellm model name."""
    not_understood: list[str] = field(default_factory=list)
    """Parts of the constraint the agent could not map onto measurable checks (said, never guessed)."""
    curriculum: dict[str, Any] = field(default_factory=dict)
    """Optional curriculum: ``{"parameter": name, "values": [...], "stage": k}`` (a relaxed target tightened
    over reflection stages); empty when none."""
    notes: str = ""
    """What changed and why (reflections fill this in)."""
    partial: bool = False
    """Written although words that change the request's meaning were not understood (:func:`meaning_lost`);
    only with ``--allow-partial`` / ``allow_partial``."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "RewardProposal":
        known = {k: v for k, v in data.items() if k in cls.__dataclass_fields__}
        return cls(**known)


@dataclass
class ReflectionContext:
    """Training feedback for one reflection (Eureka-style reward reflection)."""

    proposal: RewardProposal
    """The reward program in use."""
    stage: int
    """Reflection stage index (0 for the first reflection)."""
    component_stats: dict[str, dict[str, Any]]
    """Per reward component (``task``, ``collision``, ...): ``{"values": [sampled means over training],
    "max": float, "mean": float, "min": float}``."""
    task_success: list[float]
    """Task success rate (hand-written checker) at each evaluation so far, oldest first."""
    history: list[dict] = field(default_factory=list)
    """Earlier programs with their outcomes (from the memory), oldest first: ``{"proposal": {...},
    "outcome": {...}}``."""
    images: list[bytes] = field(default_factory=list)
    """PNG images (a grid of top-down renders of recent samples) for models that accept images."""
    sandbox_messages: list[str] = field(default_factory=list)
    """Failures reported by the sandbox since the last reflection (errors, NaNs clamped, timeouts)."""

    def summary(self) -> str:
        """The statistics as text, the way they are shown to the agent."""
        lines = [f"Reflection stage {self.stage}. Constraint: {self.proposal.constraint!r}."]
        if self.task_success:
            trend = ", ".join(f"{s:.1%}" for s in self.task_success[-10:])
            lines.append(f"Task success (independent checker) over training: {trend}")
        for name, st in self.component_stats.items():
            vals = ", ".join(f"{v:.3f}" for v in st.get("values", [])[-10:])
            lines.append(f"Reward component {name}: values [{vals}] max {st['max']:.3f} mean {st['mean']:.3f} "
                         f"min {st['min']:.3f}")
        for msg in self.sandbox_messages[-5:]:
            lines.append(f"Sandbox: {msg}")
        return "\n".join(lines)


class RewardAgentProtocol(Protocol):
    """Both the litellm agent and the offline planner serve this interface."""

    def synthesize(self, room: str, constraint: str, feedback: str | None = None) -> RewardProposal:
        """A reward program for a constraint; ``feedback`` is a sandbox/validation error of a previous try."""

    def reflect(self, context: ReflectionContext) -> RewardProposal:
        """A revised program (possibly the same, simplified, or with a curriculum) from training feedback."""
