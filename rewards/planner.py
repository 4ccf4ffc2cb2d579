"""The offline reward planner: the reward-synthesis agent when no language model is configured.

It reads a constraint the way the agent would, but with a small, readable vocabulary instead of a model (the
vocabulary and the checks: :mod:`rewards.planner_checks`; the reader: :mod:`rewards.constraint_reader`; this
module writes the program and reflects):

* **objects** ("night tables", "bedside table", "TV", "desk", "support surfaces", ...) map onto the
  Scene API's classes and groups (:data:`rewards.planner_checks.OBJECTS`);
* **quantities** ("1.0 m", "90 cm", "30 degrees", "2 night tables", "two chairs", "at least 3 ...");
* **relations and requirements** ("on either side of", "left/right of", "in front of", "behind", "facing",
  "facing away from", "turned toward", "between A and B", "view ... from", "within a 1.0 m reach", "against the
  wall", "centred on a wall", "in the middle of the room", "away from the walls", "parallel to the walls", "within
  1 m of", "A and B at least 2 m apart", "no 2 pieces of furniture closer than 0.3 m", "1 m of free space in front
  of", "a free 2 m square", "a small / spacious bedroom", "wheelchair-accessible", "turning circle", "clear path",
  "study zone", "farsighted" / "4K" for viewing distances, ...);
* **scope** (:mod:`rewards.constraint_grammar`): "every / each / all / any X" (every X, and at least one), "some
  / a X", "no X", "none of the X", "X is not / never ...", "a Y without an X ... it". Meaning-changing words no rule
  reads (a quantifier on a relation's reference, "not every", "only", "nothing") stay in ``not_understood``, so the
  command line refuses the request (:func:`rewards.proposal.meaning_lost`).

Each recognised phrase becomes a :class:`Check`: a description, the body of a small function written
against :mod:`rewards.scene_api` only, and its thresholds as named module-level UPPER_CASE constants.
Every check returns a *soft* satisfaction in [0, 1] (1 when it holds, decaying smoothly with the
distance to holding), so the reward gives partial credit that RL can climb. The program is the weighted
mean of the checks. Words it cannot map are reported in ``not_understood`` and in the reasoning, never
guessed; a constraint with nothing understood raises :class:`ValueError`. Every program passes a self-check
before it is returned (:mod:`rewards.planner_selfcheck`: hand-placed rooms that satisfy and that violate each
check must score the right way round), else :class:`ValueError`.

:meth:`OfflinePlanner.reflect` reads the task success trend: a statistically failing reward gets a
curriculum (the main threshold relaxed, then tightened stage by stage), then a simplification (softer,
denser terms), then an emphasis (more weight on the checks that need the constraint's objects, up to a
cap); a rising one is kept; a high one tightens the curriculum toward the target; sandbox failures (NaN,
errors, timeouts) give a safer program. Reflection never drops a check: every check measures part of the
constraint, and a reward without one would stop measuring it (the policy then climbs the reward while the
constraint fails). Everything is deterministic.
"""

from __future__ import annotations

import ast
import math
import textwrap
from string import Template

import numpy as np

from .constraint_reader import read_constraint
from .planner_checks import (Check, EMPHASIS_CAP, EMPHASIS_FACTOR, EMPTY_ROOM_KINDS, IMPLIED_WEIGHT, OBJECTS,
                             PRIMARY_WEIGHT, Param, Plan, SUPPORT_WEIGHT)
from .planner_selfcheck import self_check
from .proposal import ReflectionContext, RewardProposal


# --------------------------------------------------------------------------------------------------------
# Writing the program
# --------------------------------------------------------------------------------------------------------

HEADER = '''"""Reward program for: $constraint

Written by the iARCS offline planner. Each check returns a soft satisfaction in [0, 1] (1 when it holds,
decaying smoothly with the distance to holding); the reward is their weighted mean. The UPPER_CASE
constants are the thresholds; reflection relaxes or tightens them.
"""
import math
import torch

'''

HELPERS = '''

def clean(x):
    """A check's value as a finite float tensor in [0, 1]."""
    return torch.nan_to_num(x.float(), nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)


def soft_and(*parts):
    """Soft AND: the product (all parts together) blended with the mean (credit for each part)."""
    product, total = parts[0], parts[0]
    for part in parts[1:]:
        product = product * part
        total = total + part
    return AND_SHARE * product + (1.0 - AND_SHARE) * total / len(parts)
'''


def _fmt(value: float) -> str:
    return repr(round(float(value), 6))


def render(plan: Plan, values: dict[str, float] | None = None) -> str:
    """The reward program of a plan (every check); ``values`` override constants by name."""
    values = dict(values or {})
    checks = plan.checks
    if not checks:
        raise ValueError("no checks to write a reward program from")
    lines = [Template(HEADER).substitute(constraint=plan.constraint.replace('"""', "'''"))]
    lines.append("# Thresholds and softness of the checks")
    seen: set[str] = set()
    for c in checks:
        for p in c.params:
            if p.name not in seen:          # shared softness constants (COUNT_SCALE) are written once
                seen.add(p.name)
                lines.append(f"{p.name} = {_fmt(values.get(p.name, p.value))}  # {p.comment}")
    shared = [("AND_SHARE", 0.5, "soft AND: share of the product (the rest is the mean of the parts)")]
    if any("PARTIAL_CREDIT" in c.body for c in checks):
        shared += [("PARTIAL_CREDIT", 1, "1: add partial-credit calls with a smaller free-space radius"),
                   ("PARTIAL_SHRINK", 0.7, "radius factor of those partial-credit calls")]
    for name, default, comment in shared:
        value = values.get(name, default)
        lines.append(f"{name} = {int(value) if name == 'PARTIAL_CREDIT' else _fmt(value)}  # {comment}")
    lines.append("")
    lines.append("# Weights of the checks (relations that carry the constraint weigh more)")
    for c in checks:
        lines.append(f"W_{c.key.upper()} = {_fmt(values.get('W_' + c.key.upper(), c.weight))}")
    lines.append(HELPERS)
    for c in checks:
        body = Template(c.body).substitute({p.name: p.name for p in c.params})
        doc = textwrap.fill(c.description[0].upper() + c.description[1:] + ".", width=110,
                            initial_indent='    """', subsequent_indent="    ") + '"""'
        lines.append(f"\ndef check_{c.key}(scene):\n{doc}\n{body}")
    terms = [f"W_{c.key.upper()} * clean(check_{c.key}(scene))" for c in checks]
    total = " + ".join(f"W_{c.key.upper()}" for c in checks)
    lines.append("\ndef reward(scene):\n    \"\"\"Weighted mean of the checks, in [0, 1].\"\"\"\n"
                 "    total = (" + "\n             + ".join(terms) + ")\n"
                 f"    return total / ({total})\n")
    return "\n".join(lines)


#: Scenes per request to the sandbox worker when scoring many rooms.
SCORE_CHUNK = 256
_SANDBOXES: dict = {}


def _sandbox(room: str):
    """A reward sandbox for ``room``, started once per process and reused (a worker takes about a second to start;
    loading a program into it a few milliseconds). Closed when the process exits."""
    import atexit

    from .sandbox import RewardSandbox

    if room not in _SANDBOXES or _SANDBOXES[room].pid is None:
        _SANDBOXES[room] = box = RewardSandbox(room=room)
        atexit.register(box.close)
    return _SANDBOXES[room]


def program_values(code: str, room: str, layouts) -> np.ndarray:
    """The ``reward(scene)`` of a program on layouts, (n,), run in the reward sandbox like every written program
    (the planner's own included). A program that does not load or fails raises ValueError with the reason."""
    from iarcs_env.scene import SceneBatch

    box = _sandbox(room)
    loaded = box.load(code)
    if not loaded.ok:
        raise ValueError(loaded.message)
    layouts = list(layouts)
    values = []
    for start in range(0, len(layouts), SCORE_CHUNK):
        scored = box.score(SceneBatch.from_layouts(layouts[start:start + SCORE_CHUNK], room))
        if not scored.ok:
            raise ValueError(scored.message)
        values.append(scored.values)
    return np.concatenate(values)


def run_program(code: str, plan: Plan, layouts) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A program of ``plan`` on layouts, in the sandbox: its reward and each check's clean value, (n,) each (a check
    is scored as the same program with ``reward`` returning that check alone)."""
    parts = {c.key: program_values(f"{code}\n\ndef reward(scene):\n    return clean(check_{c.key}(scene))\n",
                                   plan.room, layouts) for c in plan.checks}
    return program_values(code, plan.room, layouts), parts


def program_constants(code: str) -> dict[str, float]:
    """Module-level ``NAME = number`` constants of a program (UPPER_CASE names only)."""
    out: dict[str, float] = {}
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return out
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            name = node.targets[0].id
            if name.isupper():
                try:
                    value = ast.literal_eval(node.value)
                except ValueError:
                    continue
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    out[name] = float(value)
    return out


# --------------------------------------------------------------------------------------------------------
# The planner
# --------------------------------------------------------------------------------------------------------

#: Reflection: success below LOW and not rising is failing; at or above HIGH it is time to tighten.
LOW_SUCCESS = 0.15
HIGH_SUCCESS = 0.6
MIN_GAIN = 0.02
WINDOW = 6
CURRICULUM_STEPS = 2


def success_trend(success: list[float]) -> tuple[str, str]:
    """Classify a task success series as ``unknown``, ``failing``, ``rising``, ``high`` or ``flat``, with
    the numbers behind it. Rising = the later half of the last WINDOW evaluations beats the earlier half
    by more than MIN_GAIN and by more than two standard errors of the difference."""
    values = [float(v) for v in success if v is not None and math.isfinite(float(v))]
    if len(values) < 2:
        return "unknown", f"only {len(values)} evaluation(s) of task success so far"
    window = values[-WINDOW:]
    half = len(window) // 2
    early, late = window[:half], window[half:]
    m1, m2 = sum(early) / len(early), sum(late) / len(late)

    def var(xs, m):
        return sum((x - m) ** 2 for x in xs) / max(len(xs) - 1, 1)

    se = math.sqrt(var(early, m1) / len(early) + var(late, m2) / len(late))
    gain = m2 - m1
    facts = (f"task success {', '.join(f'{v:.1%}' for v in window)}: later half {m2:.1%} vs earlier half "
             f"{m1:.1%} (gain {gain:+.1%}, 2 s.e. {2 * se:.1%})")
    if window[-1] >= HIGH_SUCCESS:
        return "high", facts
    if gain > max(MIN_GAIN, 2 * se):
        return "rising", facts
    if m2 < LOW_SUCCESS:
        return "failing", facts
    return "flat", facts


class OfflinePlanner:
    """The deterministic, offline reward-synthesis agent (see the module docstring)."""

    source = "offline"

    def plan(self, room: str, constraint: str) -> Plan:
        """The checks for a constraint; raises ValueError when nothing in it can be measured."""
        if not constraint or not constraint.strip():
            raise ValueError("empty constraint: nothing to write a reward for")
        plan = read_constraint(constraint, room)
        if not plan.checks:
            raise ValueError(
                f"the offline planner could not map any part of {constraint!r} onto a measurable check "
                f"(not understood: {', '.join(plan.not_understood) or 'everything'}). It knows objects such as "
                f"{', '.join(sorted({e.label for e in OBJECTS.values()}))} and requirements such as counts, "
                f"heights ('within a 1.0 m reach'), 'on either side of', 'left/right of', 'in front of', 'behind', "
                f"'facing', 'facing away from', 'between', 'view ... from', 'within X m of', 'at least X m apart', "
                f"'against the wall', 'centred on a wall', 'in the middle of the room', 'parallel to the walls', "
                f"'free space in front of', 'a free 2 m square', 'a small bedroom', 'wheelchair-accessible', "
                f"'turning circle', 'clear path', 'study zone'.")
        return plan

    def synthesize(self, room: str, constraint: str, feedback: str | None = None) -> RewardProposal:
        """A reward program for the constraint. With ``feedback`` (a sandbox failure of a previous try) the
        program is written in its conservative form (no extra partial-credit free-space calls)."""
        plan = self.plan(room, constraint)
        values = {"PARTIAL_CREDIT": 0} if feedback else {}
        code = render(plan, values)
        problems = self_check(plan, lambda layouts: run_program(code, plan, layouts))
        if problems:
            raise ValueError(f"the offline planner's self-check refused its program for {constraint!r}: "
                             + "; ".join(problems) + ". Rephrase the request or use an LLM (--model)")
        notes = ""
        if feedback:
            notes = (f"Previous attempt failed: {feedback.strip()[:300]}. Wrote the conservative form: every "
                     f"check is NaN-guarded and clamped, and the extra free-space calls are off.")
        return RewardProposal(constraint=constraint, reasoning=self.reasoning(plan), decomposition=self.decompose(plan),
                              code=code, weight=1.0, room=room, source=self.source,
                              not_understood=list(plan.not_understood), notes=notes)

    # -- explanation ----------------------------------------------------------------------------------
    @staticmethod
    def decompose(plan: Plan, values: dict[str, float] | None = None) -> list[str]:
        out = []
        for c in plan.checks:
            consts = ", ".join(f"{p.name}={_fmt((values or {}).get(p.name, p.value))}"
                               for p in c.params if p.kind == "threshold")
            weight = (values or {}).get(f"W_{c.key.upper()}", c.weight)
            out.append(f"{c.key} (weight {weight:g}): {c.description}" + (f" [{consts}]" if consts else ""))
        return out

    @staticmethod
    def reasoning(plan: Plan) -> str:
        parts = [f"Constraint: {plan.constraint!r} in a {plan.room}."]
        parts.append("Understood: " + "; ".join(plan.understood) + ".")
        parts.extend(plan.assumptions)
        parts.append(
            f"I measure it with {len(plan.checks)} check(s): "
            + ", ".join(c.key for c in plan.checks) + ". Each returns a soft satisfaction in [0, 1] that "
            "rises as the scene gets closer to the target (exponential decay outside the thresholds, soft AND "
            "= product blended with the mean), so training gets partial credit instead of a 0/1 signal; the "
            "reward is their weighted mean.")
        roles = {PRIMARY_WEIGHT: "the requirement itself", SUPPORT_WEIGHT: "a count or object the user named",
                 IMPLIED_WEIGHT: "objects a relation needs, a little credit for having them"}
        weights = sorted({c.weight for c in plan.checks}, reverse=True)
        if len(weights) > 1:
            parts.append("Weights: " + "; ".join(
                f"{', '.join(c.key for c in plan.checks if c.weight == w)} {w:g} ({roles.get(w, 'custom')})"
                for w in weights) + ".")
        elif len(plan.checks) > 1:
            parts.append("The checks weigh the same: each is one part of the requirement.")
        if plan.not_understood:
            parts.append("Ignored (no measurable meaning in my vocabulary, not guessed): "
                         + ", ".join(repr(w) for w in plan.not_understood) + ".")
        return " ".join(parts)

    # -- reflection -----------------------------------------------------------------------------------
    def reflect(self, context: ReflectionContext) -> RewardProposal:
        """A revised proposal from training feedback (see the module docstring); ``notes`` says why."""
        old = context.proposal
        try:
            plan = self.plan(old.room, old.constraint)
        except ValueError as err:
            return RewardProposal(**{**old.to_dict(), "notes": f"Stage {context.stage}: the offline planner cannot "
                                     f"revise this program ({err}); keeping it unchanged."})
        mine = old.source == self.source
        values = program_constants(old.code) if mine else {}
        # a program of mine without one of the plan's checks (an earlier planner version dropped it)
        missing = [c.key for c in plan.checks if mine and f"def check_{c.key}(" not in old.code]
        curriculum = dict(old.curriculum or {}) if mine else {}
        success = list(context.task_success)
        changed_at = curriculum.get("changed_at")
        if changed_at is not None and not 0 < changed_at <= len(success):   # a history that does not match
            changed_at = None
        since = success[max(changed_at - 1, 0):] if changed_at is not None else success
        trend, facts = success_trend(since)
        notes = [f"Stage {context.stage}: {facts}" + (" (since the last change)." if changed_at is not None else ".")]
        task_stats = context.component_stats.get("task", {})
        if task_stats:
            notes.append(f"Task reward mean {task_stats.get('mean', float('nan')):.3f} "
                         f"(max {task_stats.get('max', float('nan')):.3f}).")
        problems = [m for m in context.sandbox_messages if m]

        if problems:
            action = self._safer(values, problems, mine, notes)
        elif trend == "high":
            action = self._tighten(plan, values, curriculum, notes, reason="success is high")
        elif trend == "rising":
            action = "keep"
            notes.append("Success is rising: keep the program unchanged.")
        elif trend == "failing" and changed_at is not None and len(success) - changed_at < 2:
            action = "keep"
            notes.append(f"Only {len(success) - changed_at} evaluation(s) since the last change: too early to "
                         f"judge it, keep it.")
        elif trend == "failing" and success_trend(task_stats.get("values", []))[0] == "rising":
            action = "keep"
            notes.append("Success is low, but the task reward is still climbing: give it time, keep the program.")
        elif trend == "failing":
            action = self._relax(plan, values, curriculum, notes)
        elif trend == "flat" and curriculum.get("stage", 0) < len(curriculum.get("values", [])) - 1:
            action = self._tighten(plan, values, curriculum, notes,
                                   reason="success has settled at the relaxed stage")
        else:
            action = "keep"
            notes.append("Not enough evidence to change the reward: keep it." if trend == "unknown" else
                         "Success is flat but not failing and there is nothing to tighten: keep it.")
        if missing:
            notes.append(f"The program in use lacks {', '.join(missing)} (dropped by an earlier planner version): "
                         f"bring it back, a reward without a check the constraint requires stops measuring it.")
            action = "restore" if action == "keep" else action
        code = old.code
        if action != "keep":
            code = render(plan, values)
            problems = self_check(plan, lambda layouts: run_program(code, plan, layouts))
            if problems:            # the revision would rank the plan's own example rooms the wrong way round
                notes.append(f"The revised program ({action}) failed the self-check ({'; '.join(problems)}): keep "
                             f"the program in use.")
                return RewardProposal(**{**old.to_dict(), "notes": " ".join(notes)})
            if curriculum:
                curriculum["changed_at"] = len(success)
            if code == old.code:
                action = "keep"
        return RewardProposal(constraint=old.constraint, reasoning=self.reasoning(plan) + f" Reflection: {action}.",
                              decomposition=self.decompose(plan, values), code=code, weight=old.weight,
                              room=old.room, source=self.source, not_understood=list(plan.not_understood),
                              curriculum=curriculum, notes=" ".join(notes))

    @staticmethod
    def _safer(values: dict, problems: list[str], mine: bool, notes: list[str]) -> str:
        """Sandbox failures: the guarded program, without the extra free-space calls."""
        notes.append(f"The sandbox reported {len(problems)} problem(s) (last: {problems[-1][:200]}).")
        if not mine:
            notes.append("The program in use was not written by me: replace it by the planner's guarded program "
                         "(every check NaN-guarded and clamped to [0, 1]).")
        if "PARTIAL_CREDIT" in values and values["PARTIAL_CREDIT"]:
            values["PARTIAL_CREDIT"] = 0
            notes.append("Safer program: the extra partial-credit free-space calls are off (fewer grid "
                         "computations, less time and memory per batch); thresholds kept.")
        elif mine:
            notes.append("My program already guards every check (clean(): NaN -> 0, clamp to [0, 1]) and makes "
                         "no optional expensive calls: nothing safer to write, keep it.")
            return "keep"
        return "safer"

    @staticmethod
    def _primary(plan: Plan) -> tuple[Check, Param] | None:
        for c in sorted(plan.checks, key=lambda c: -c.weight):
            if c.curriculum:
                return c, next(p for p in c.params if p.name == c.curriculum)
        return None

    def _relax(self, plan: Plan, values: dict, curriculum: dict, notes: list[str]) -> str:
        """Failing: start a curriculum, step it back, simplify (softer, denser terms), then emphasise the checks
        that need the constraint's objects (see :meth:`_emphasise`). Never drops a check."""
        target = self._primary(plan)
        if not curriculum and target is not None:
            check, p = target
            steps = [round(p.value + p.relax * k, 6) for k in range(CURRICULUM_STEPS, -1, -1)]
            curriculum.update(parameter=p.name, values=steps, stage=0, target=p.value)
            values[p.name] = steps[0]
            notes.append(f"Success is low and not improving: the reward is failing. Curriculum on {p.name} "
                         f"({p.comment}): start relaxed at {steps[0]:g}, tighten over later stages through "
                         f"{', '.join(f'{v:g}' for v in steps[1:])} (the target).")
            return "curriculum"
        if curriculum.get("stage", 0) > 0:
            curriculum["stage"] -= 1
            values[curriculum["parameter"]] = curriculum["values"][curriculum["stage"]]
            notes.append(f"Success fell back after tightening: step the curriculum back to "
                         f"{curriculum['parameter']} = {values[curriculum['parameter']]:g}.")
            return "curriculum"
        if values.get("AND_SHARE", 0.5) >= 0.5:
            for c in plan.checks:
                for p in c.params:
                    if p.kind == "scale":
                        values[p.name] = p.value * 2
            values["AND_SHARE"] = 0.25
            notes.append("Still failing at the most relaxed stage: simplify. The soft terms decay half as fast "
                         "(every *_SCALE doubled) and the soft AND leans on the mean of its parts (AND_SHARE "
                         "0.25), so partial progress on the hardest check earns more credit.")
            return "simplification"
        return self._emphasise(plan, values, notes)

    @staticmethod
    def _emphasised(plan: Plan) -> list[Check]:
        """The checks an emphasis step weighs up: the requirement checks that need their objects (relations,
        heights, walls, a turning circle next to an object) and the existence of the objects a relation
        needs (has_bed, ...). Counts, named objects and the checks an emptier room satisfies keep theirs."""
        return [c for c in plan.checks
                if (c.weight >= PRIMARY_WEIGHT and c.entities and c.kind not in EMPTY_ROOM_KINDS
                    and c.scope not in ("none", "without"))
                or (c.kind == "exists" and c.weight == IMPLIED_WEIGHT)]

    def _emphasise(self, plan: Plan, values: dict, notes: list[str]) -> str:
        """Still failing after relaxing and simplifying: multiply the weights of :meth:`_emphasised` checks by
        EMPHASIS_FACTOR, up to EMPHASIS_CAP times their original weight; at the cap, keep the program."""
        never = ("No check is dropped: each measures part of the constraint, and a reward without one would "
                 "rise while the constraint fails.")
        targets = self._emphasised(plan)
        others = [c for c in plan.checks if c not in targets]
        if not targets or not others:
            why = ("no check needs the constraint's objects" if not targets else
                   "every check needs the constraint's objects, and raising all weights together leaves the "
                   "weighted mean unchanged")
            notes.append(f"Still failing after relaxing and simplifying; an emphasis would change nothing ({why}). "
                         f"{never} Keep the program and leave it to the next reflection (or a language model) "
                         f"to rethink the decomposition.")
            return "keep"
        raised = []
        for c in targets:
            name = f"W_{c.key.upper()}"
            now = values.get(name, c.weight)
            new = round(min(now * EMPHASIS_FACTOR, c.weight * EMPHASIS_CAP), 6)
            if new > now:
                values[name] = new
                raised.append(f"{name} {now:g} -> {new:g}")
        if not raised:
            notes.append(f"Still failing, and the checks that need the constraint's objects "
                         f"({', '.join(c.key for c in targets)}) are already at {EMPHASIS_CAP:g}x their original "
                         f"weight, the cap of the emphasis. {never} Keep the program and leave it to the next "
                         f"reflection (or a language model) to rethink the decomposition.")
            return "keep"
        rest = ", ".join(c.key for c in others) + (" keeps its" if len(others) == 1 else " keep their")
        notes.append(f"Still failing after relaxing and simplifying: emphasise the checks that need the constraint's "
                     f"objects ({'; '.join(raised)}; at most {EMPHASIS_CAP:g}x the original weight), so the reward "
                     f"pays more for them; {rest} weight. {never}")
        return "emphasis"

    def _tighten(self, plan: Plan, values: dict, curriculum: dict, notes: list[str], reason: str) -> str:
        """Move the curriculum one stage toward its target; at the target undo the simplification (an
        emphasis stays: it makes the reward measure the constraint more, not less)."""
        if curriculum.get("stage", 0) < len(curriculum.get("values", [])) - 1:
            curriculum["stage"] += 1
            values[curriculum["parameter"]] = curriculum["values"][curriculum["stage"]]
            final = curriculum["stage"] == len(curriculum["values"]) - 1
            notes.append(f"Tighten ({reason}): {curriculum['parameter']} = {values[curriculum['parameter']]:g}"
                         + (" (the final target)." if final else "."))
            return "tighten"
        if values.get("AND_SHARE", 0.5) < 0.5:
            for c in plan.checks:
                for p in c.params:
                    if p.kind == "scale":
                        values[p.name] = p.value
            values["AND_SHARE"] = 0.5
            emphasised = [c.key for c in plan.checks if values.get(f"W_{c.key.upper()}", c.weight) > c.weight]
            kept = (f"; {', '.join(emphasised)} keep their emphasised weight" if emphasised else "")
            notes.append(f"Tighten ({reason}): restore the original softness{kept}.")
            return "tighten"
        notes.append(f"{reason[0].upper() + reason[1:]} and the program is at its final target: keep it.")
        return "keep"
