"""Stage 2 (paper section 3.4): a task reward written by the reward-synthesis agent from a natural-language
constraint, added to the universal rewards, and refined from training feedback.

- :class:`TaskConfig` is the ``task:`` block of a training YAML.
- :func:`setup_task_reward` asks the agent (an LLM through litellm, or the offline planner) for a reward
  program, or takes the current one from the run's reward evolution memory when the run resumes, and loads
  it into a sandbox (:class:`rewards.sandbox.SandboxedReward`; close ``reward.sandbox`` when done).
- :class:`ReflectionCallback` collects, every epoch, each reward component's mean and the task success
  rate of the rollouts (the hand-written checker of ``iarcs_env.tasks``, never the generated reward), and
  every ``reflect_every`` epochs hands them to the agent with the previous programs and a grid of renders
  (reward reflection); an accepted new program replaces the reward in place, a failing one is recorded and
  training keeps the last good reward.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .callbacks import BaseCallback, render_grid_tensor

MEMORY_FILE = "reward_memory.json"


@dataclass
class TaskConfig:
    """The stage-2 task of a training run."""

    constraint: str = ""
    """The natural-language constraint; empty: the prompt of ``checker``'s paper task."""
    checker: str = ""
    """Task success checker (``iarcs_env.tasks``: reach_1m, tv_from_bed, study_zone, two_nightstands,
    wheelchair) used for evaluation and reflection; empty: none (reflection then sees rewards only)."""
    reflect_every: int = 10
    """K: reflect on the reward every K epochs (0: never)."""
    model: str = ""
    """litellm model (e.g. gemini/gemini-2.5-pro, openai/NAME with api_base, ollama/NAME); empty: the offline
    planner."""
    api_base: str = ""
    """Server URL for openai-compatible or ollama models."""
    llm: dict = field(default_factory=dict)
    """Further rewards.llm.LLMConfig settings (timeout, max_retries, temperature, cache_dir, ...)."""
    weight: float = 0.0
    """Weight of the task reward; 0: the weight the agent proposes."""
    sandbox_timeout: float = 30.0
    """Per-batch deadline of the reward program, seconds."""
    allow_partial: bool = False
    """Train on a program written without words that change the request's meaning (else the run refuses)."""

    def resolved_constraint(self) -> str:
        if self.constraint:
            return self.constraint
        if self.checker:
            from iarcs_env.tasks import get_task

            return get_task(self.checker).prompt
        raise ValueError("the task block needs a 'constraint' (or a 'checker' naming a paper task)")


def task_config(data: dict, where: str = "task") -> TaskConfig:
    from .config import dataclass_from_dict

    cfg = dataclass_from_dict(TaskConfig, data, where)
    if cfg.reflect_every < 0:
        raise ValueError(f"{where}: reflect_every must be >= 0, got {cfg.reflect_every}")
    return cfg


def make_task_agent(cfg: TaskConfig, sandbox=None, run_dir: Path | None = None):
    """The reward-synthesis agent of a task: the litellm agent when a model is configured (its answers
    cached in ``run_dir/llm_cache`` unless the config names a cache), else the offline planner."""
    from rewards.agent import make_agent

    if not cfg.model:
        return make_agent(None, sandbox=sandbox)
    llm = {"cache_dir": str(Path(run_dir) / "llm_cache")} if run_dir is not None else {}
    llm.update(cfg.llm)
    return make_agent(cfg.model, api_base=cfg.api_base or None, sandbox=sandbox, **llm)


def llm_usage(agent) -> dict | None:
    """Token, cost and call totals of an LLM agent (None for the offline planner)."""
    client = getattr(agent, "client", None)
    return client.usage.to_dict() if client is not None else None


def synthesize_checked(agent, sandbox, room: str, constraint: str, attempts: int = 3, allow_partial: bool = False):
    """Ask ``agent`` for a program until ``sandbox`` accepts (loads) one; returns ``(proposal, messages)``. A program
    written without words that change the request's meaning (:func:`rewards.proposal.meaning_lost`) is refused
    (ValueError) unless ``allow_partial``; then it is marked ``partial``."""
    from rewards.proposal import meaning_lost

    feedback, messages = None, []
    for _ in range(attempts):
        proposal = agent.synthesize(room, constraint, feedback=feedback)
        result = sandbox.load(proposal.code)
        if result.ok:
            lost = meaning_lost(proposal.not_understood)
            if lost and not allow_partial:
                who = "the offline planner" if proposal.source == "offline" else proposal.source
                raise ValueError(
                    f"{who} did not understand {', '.join(repr(w) for w in lost)} in {constraint!r}; those words "
                    "change what is asked, so a program without them could reward something else or the opposite. "
                    "Rephrase the request (what the planner understands: docs/results/planner_requests.md, "
                    "`iarcs reward synthesize --help`), use an LLM (--model), or pass --allow-partial (allow_partial: "
                    "true in a task config) to use the program anyway, marked partial")
            proposal.partial = bool(lost)
            return proposal, messages
        feedback = result.message
        messages.append(result.message)
    raise ValueError(f"the reward agent produced no program the sandbox accepts for {constraint!r}: "
                     + " | ".join(messages))


def setup_task_reward(cfg: TaskConfig, room: str, run_dir: Path, log=print):
    """``(task_reward, agent, memory, proposal)`` for a run: the program in the run's memory when resuming,
    else a fresh one from the agent, loaded into a sandboxed reward."""
    from rewards.memory import EvolutionMemory
    from rewards.sandbox import RewardSandbox, SandboxedReward

    constraint = cfg.resolved_constraint()
    memory = EvolutionMemory.open(Path(run_dir) / MEMORY_FILE, constraint, room)
    sandbox = RewardSandbox(room=room, timeout=cfg.sandbox_timeout)
    agent = make_task_agent(cfg, sandbox=sandbox, run_dir=run_dir)
    proposal = memory.current()
    if proposal is not None:
        result = sandbox.load(proposal.code)
        if not result.ok:
            sandbox.close()
            raise ValueError(f"the reward program in {memory.path} no longer loads: {result.message}")
        log(f"task reward: the current program of {memory.path} (stage {memory.stages()})")
    else:
        try:
            proposal, failures = synthesize_checked(agent, sandbox, room, constraint, allow_partial=cfg.allow_partial)
        except Exception:
            sandbox.close()
            raise
        memory.record("synthesize", 0, proposal, accepted=True, message=" | ".join(failures))
        log(f"task reward: written by {proposal.source} for {constraint!r}"
            + (f"; not understood: {', '.join(proposal.not_understood)}" if proposal.not_understood else ""))
    return SandboxedReward(sandbox), agent, memory, proposal


def png_bytes(image: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return buf.getvalue()


class ReflectionCallback(BaseCallback):
    """Reward reflection every ``every`` epochs (see the module docstring). The ``task`` weight of the
    environment's composite reward follows the accepted proposal's weight unless ``fixed_weight`` is set."""

    def __init__(self, agent, task_reward, memory, every: int = 10, checker: Callable | None = None,
                 fixed_weight: float = 0.0, n_render: int = 16, verbose: int = 1):
        super().__init__(verbose)
        self.agent, self.task_reward, self.memory = agent, task_reward, memory
        self.every, self.checker = every, checker
        self.fixed_weight, self.n_render = fixed_weight, n_render
        self.components: dict[str, list[float]] = {}  # per epoch since the last reflection
        self.success = memory.task_success_history()  # per epoch over the whole run (the agent judges trends)
        self.window_start = len(self.success)  # where the current feedback window starts

    def _on_step(self) -> bool:
        for key, value in self.locals.items():
            if key.startswith("reward_") and key != "reward_std":
                self.components.setdefault(key[len("reward_"):], []).append(float(value))
        scene = getattr(self.model, "_last_scene", None)
        if self.checker is not None and scene is not None:
            rate = float(np.mean(self.checker(scene)))
            self.success.append(rate)
            if self.model.writer:
                self.model.writer.add_scalar("task/success_rollout", rate, self.model.num_timesteps)
        if self.every and self.model.epoch % self.every == 0:
            self.reflect(scene)
        return True

    def component_stats(self) -> dict[str, dict]:
        """Eureka-style statistics of each reward component since the last reflection."""
        return {name: {"values": [round(v, 4) for v in vals], "max": float(np.max(vals)),
                       "mean": float(np.mean(vals)), "min": float(np.min(vals))}
                for name, vals in self.components.items() if vals}

    def reflect(self, scene=None) -> None:
        from iarcs_env.render import image_grid, render_layout
        from rewards.proposal import ReflectionContext

        current = self.memory.current()
        renders = [render_layout(l) for l in scene.to_layouts()[: self.n_render]] if scene is not None else []
        images = [png_bytes(image_grid(renders, cols=4))] if renders else []
        outcome = {"epoch": self.model.epoch, "task_success": [round(s, 4) for s in self.success[self.window_start:]],
                   "component_stats": self.component_stats()}
        context = ReflectionContext(proposal=current, stage=self.memory.stages(),
                                    component_stats=outcome["component_stats"], task_success=list(self.success),
                                    history=self.memory.history(), images=images,
                                    sandbox_messages=self.task_reward.take_messages())
        epoch = self.model.epoch
        try:
            proposal = self.agent.reflect(context)
        except Exception as err:  # an agent failure must never stop training: keep the last good reward
            self.memory.record("reflect", epoch, current, accepted=False, message=f"agent failed: {err}",
                               outcome=outcome)
            self._say(f"reflection at epoch {epoch}: the agent failed ({err}); keeping the current reward")
            self._reset()
            return
        changed = proposal.code != current.code or proposal.weight != current.weight
        result = self.task_reward.load(proposal.code) if changed else None
        accepted = result is None or result.ok
        self.memory.record("reflect", epoch, proposal, accepted=accepted,
                           message="" if result is None else result.message, outcome=outcome)
        if accepted:
            self.model.venv.reward_fn.weights["task"] = self.fixed_weight or proposal.weight
        verdict = ("kept the program" if not changed else "new program accepted" if accepted
                   else f"new program rejected by the sandbox ({result.message}); keeping the last good one")
        usage = llm_usage(self.agent)
        self._say(f"reflection at epoch {epoch}: {verdict}. {proposal.notes}".strip()
                  + (f" [LLM so far: {usage}]" if usage else ""))
        if self.model.writer:
            self.model.writer.add_text("task/reflection", f"epoch {epoch}: {verdict}\n\n{proposal.notes}\n\n"
                                       + "\n".join("    " + line for line in proposal.code.splitlines()),
                                       self.model.num_timesteps)
            if renders:
                self.model.writer.add_image("task/reflection_samples", render_grid_tensor(renders),
                                            self.model.num_timesteps)
        self._reset()

    def _reset(self) -> None:
        self.components, self.window_start = {}, len(self.success)

    def _say(self, text: str) -> None:
        if self.verbose:
            print(text)


def save_task_outputs(run_dir: Path, memory, agent=None) -> Path:
    """The final reward program and its record beside the run's adapter: ``reward/program.py``,
    ``reward/proposal.json`` and, for an LLM agent, ``reward/llm_usage.json`` (tokens, cost, calls)."""
    proposal = memory.current()
    out = Path(run_dir) / "reward"
    out.mkdir(parents=True, exist_ok=True)
    (out / "program.py").write_text(proposal.code)
    (out / "proposal.json").write_text(json.dumps(proposal.to_dict(), indent=1))
    usage = llm_usage(agent)
    if usage:
        (out / "llm_usage.json").write_text(json.dumps(usage, indent=1))
    return out
