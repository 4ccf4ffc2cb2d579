"""``iarcs reward synthesize`` (the reward-synthesis agent alone: constraint -> program) and ``iarcs reward
score`` (a program's reward for every scene of a file, run in the sandbox)."""

from __future__ import annotations

import json
from pathlib import Path

from experiments.cli import finite_float


def add_agent_options(p) -> None:
    """The options that choose the reward-synthesis agent (shared with ``iarcs generate``)."""
    p.add_argument("--model", default=None,
                   help="litellm model, e.g. gemini/gemini-2.5-pro, openai/NAME (with --api-base), ollama/NAME; "
                        "default: the offline planner (no network)")
    p.add_argument("--api-base", default=None, help="server URL for openai-compatible or ollama models")
    p.add_argument("--timeout", type=finite_float, default=120.0, help="seconds per LLM request (default 120)")
    p.add_argument("--max-seconds", type=finite_float, default=240.0,
                   help="longest one synthesis or reflection may take, retries included (default 240)")
    p.add_argument("--allow-partial", action="store_true",
                   help="use a program although words that change the request's meaning (not, away, every, ...) "
                        "were not understood; it is marked partial")


def register(sub) -> None:
    p = sub.add_parser("reward", help="write a reward program for a constraint, or score scenes with one")
    rsub = p.add_subparsers(dest="reward_command", metavar="ACTION")
    rsub.required = True

    s = rsub.add_parser("synthesize", help="turn a natural-language constraint into a reward program")
    s.add_argument("--room", default="bedroom", help="bedroom, livingroom or diningroom (default bedroom)")
    s.add_argument("--constraint", required=True, help='e.g. "A bedroom with 2 night tables on either side of the bed"')
    s.add_argument("--out", required=True, help="program .py; its reasoning and decomposition go to the .json beside it")
    add_agent_options(s)
    s.set_defaults(func=cmd_synthesize)

    s = rsub.add_parser("score", help="score every scene of a layout file with a reward program (sandboxed)")
    s.add_argument("--program", required=True, help="reward program .py (defines reward(scene))")
    s.add_argument("--scenes", required=True, help="layouts: neutral .json or an ATISS folder")
    s.add_argument("--out", required=True, help="scores .json: a list of numbers in scene order")
    s.add_argument("--room", default=None, help="room type (default: the file's)")
    s.add_argument("--batch-size", type=int, default=64, help="scenes per sandbox batch (default 64)")
    s.add_argument("--timeout", type=finite_float, default=60.0, help="deadline per batch, seconds (default 60)")
    s.set_defaults(func=cmd_score)


def synthesize(room: str, constraint: str, model: str | None = None, api_base: str | None = None,
               timeout: float = 120.0, max_seconds: float = 240.0, allow_partial: bool = False, log=print):
    """A sandbox-checked proposal from the configured agent (an LLM or the offline planner)."""
    from agents.stage2 import synthesize_checked
    from iarcs_env.rooms import get_room
    from rewards.agent import make_agent
    from rewards.sandbox import RewardSandbox

    room = get_room(room).name
    if not constraint.strip():
        raise ValueError("--constraint is empty; describe the scene you want, e.g. "
                         '"A bedroom with 2 night tables on either side of the bed"')
    llm = {"timeout": timeout, "max_seconds": max_seconds} if model else {}
    with RewardSandbox(room=room) as sandbox:
        agent = make_agent(model, api_base=api_base, sandbox=sandbox, **llm)
        log(f"writing a reward program with {'the offline planner' if not model else model} ...")
        proposal, _ = synthesize_checked(agent, sandbox, room, constraint, allow_partial=allow_partial)
    return proposal


def write_proposal(proposal, path: Path) -> tuple[Path, Path]:
    """The program at ``path`` (.py) and everything else the agent said at the .json beside it."""
    path = Path(path)
    if path.suffix != ".py":
        path = path.with_suffix(".py")
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (f"# Reward program for: {proposal.constraint}\n# Written by: {proposal.source}; weight "
              f"{proposal.weight:g} next to the universal rewards. Reasoning: {path.with_suffix('.json').name}\n")
    if proposal.partial:
        header += f"# PARTIAL: written without {', '.join(proposal.not_understood)} (--allow-partial)\n"
    path.write_text(header + proposal.code.rstrip() + "\n")
    meta = path.with_suffix(".json")
    meta.write_text(json.dumps(proposal.to_dict(), indent=1))
    return path, meta


def cmd_synthesize(args) -> int:
    proposal = synthesize(args.room, args.constraint, args.model, args.api_base, args.timeout, args.max_seconds,
                          args.allow_partial)
    program, meta = write_proposal(proposal, Path(args.out))
    print("decomposition:\n" + "\n".join(f"  - {d}" for d in proposal.decomposition))
    if proposal.not_understood:
        print("not understood (ignored): " + ", ".join(proposal.not_understood))
    partial = " PARTIAL: it ignores words that change what was asked" if proposal.partial else ""
    print(f"program: {program} (weight {proposal.weight:g}){partial}; reasoning and decomposition: {meta}")
    return 0


def score_layouts(code: str, layouts, batch_size: int = 64, timeout: float = 60.0, progress: bool = True):
    """The program's reward for every layout, in order, and how many values the sandbox replaced: (values,
    NaN/inf, finite values beyond its clamp bound)."""
    import numpy as np
    from tqdm import tqdm

    from iarcs_env.scene import SceneBatch
    from rewards.sandbox import RewardSandbox

    room = layouts[0].room_type
    values, nonfinite, clipped = [], 0, 0
    with RewardSandbox(room=room, timeout=timeout) as sandbox:
        loaded = sandbox.load(code)
        if not loaded.ok:
            raise ValueError(f"the program does not load: {loaded.message}")
        for start in tqdm(range(0, len(layouts), batch_size), desc="scoring", unit="batch", disable=not progress):
            part = layouts[start:start + batch_size]
            result = sandbox.score(SceneBatch.from_layouts(part, num_slots=max(len(l) for l in part) or 1))
            if not result.ok:
                raise ValueError(f"scenes {start}..{start + len(part) - 1}: {result.message}")
            values.extend(float(v) for v in result.values)
            nonfinite += result.nonfinite
            clipped += result.clipped
    return np.asarray(values), nonfinite, clipped


def cmd_score(args) -> int:
    from experiments.cli import CLIError
    from experiments.commands.evaluate import _load
    from rewards.sandbox import DEFAULT_CLAMP

    program = Path(args.program)
    if not program.exists():
        raise CLIError(f"no reward program at {program}")
    if args.batch_size < 1:
        raise CLIError(f"--batch-size must be positive, got {args.batch_size}")
    layouts = _load(args.scenes, args.room, "--scenes")
    values, nonfinite, clipped = score_layouts(program.read_text(), layouts, args.batch_size, args.timeout)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps([round(v, 6) for v in values.tolist()]))
    print(f"{len(values)} scenes: mean {values.mean():.4f}, min {values.min():.4f}, max {values.max():.4f}"
          + (f"; {nonfinite} NaN/inf values replaced" if nonfinite else "")
          + (f"; {clipped} values beyond +-{DEFAULT_CLAMP:g} clipped to it" if clipped else "") + f" -> {out}")
    return 0
