"""The offline reward planner (rewards.planner): the five paper prompts give sandbox-clean programs that run
on scene batches, agree with the hand-written task checkers (without calling them) and give partial credit
that grows toward satisfaction; unknown words are reported, not guessed; reflection is deterministic."""

import math
import re

import numpy as np
import pytest
import torch

from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.scene import SceneBatch
from iarcs_env.tasks import TASKS, task_results
from rewards.constraint_reader import read_constraint
from rewards.planner import OfflinePlanner, program_constants, render, success_trend
from rewards.planner_checks import IMPLIED_WEIGHT, NEEDS_OBJECTS
from rewards.proposal import ReflectionContext, RewardProposal
from rewards.sandbox import RewardSandbox, check_program
from rewards.scene_api import Scene
from scene_factory import box, make_layout, random_layouts

from conftest import real_file

PLANNER = OfflinePlanner()
PROGRAMS = {name: PLANNER.synthesize("bedroom", task.prompt) for name, task in TASKS.items()}
ROOM = [(0, 0), (6, 0), (6, 6), (0, 6)]


def run(code: str, layouts) -> np.ndarray:
    """The program's reward(scene) on layouts, outside the sandbox (the tests' own trusted code)."""
    namespace = {"math": math, "torch": torch}
    exec(compile(code, "<reward>", "exec"), namespace)
    values = namespace["reward"](Scene(SceneBatch.from_layouts(list(layouts), "bedroom")))
    assert values.shape == (len(layouts),)
    values = values.detach().numpy()
    assert np.isfinite(values).all() and (values >= 0).all() and (values <= 1).all()
    return values


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """Probability that an accepted scene's reward beats a rejected one's (ties count half)."""
    diff = pos[:, None] - neg[None, :]
    return float((diff > 0).mean() + 0.5 * (diff == 0).mean())


def alignment(name: str, layouts) -> tuple[float, float, float]:
    accepted = task_results(name, layouts)
    values = run(PROGRAMS[name].code, layouts)
    assert accepted.any() and (~accepted).any(), f"{name}: need accepted and rejected scenes"
    return values[accepted].mean(), values[~accepted].mean(), auc(values[accepted], values[~accepted])


# --------------------------------------------------------------------------------------------------------
# Programs
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(TASKS))
def test_paper_prompts_give_clean_programs(name):
    p = PROGRAMS[name]
    assert isinstance(p, RewardProposal) and p.source == "offline" and p.room == "bedroom"
    assert check_program(p.code) == []
    assert p.not_understood == [] and p.decomposition and "def reward(scene)" in p.code
    consts = program_constants(p.code)
    assert consts and all(k.isupper() for k in consts)
    assert "iarcs_env" not in p.code and "tasks" not in p.code  # never graded by the checker itself


def test_programs_match_the_task_definitions():
    c = {name: program_constants(p.code) for name, p in PROGRAMS.items()}
    assert c["reach_1m"]["HEIGHT_LIMIT"] == 1.0
    tv, wheel = c["tv_from_bed"], c["wheelchair"]
    assert (tv["VIEW_MIN"], tv["VIEW_MAX"], tv["VIEW_ANGLE_DEG"]) == (2, 4, 30)
    assert (c["study_zone"]["FRONT_DEPTH"], c["study_zone"]["FRONT_MARGIN"]) == (0.9, 0.1)
    assert c["two_nightstands"]["SIDE_GAP"] == 0.5 and c["two_nightstands"]["NIGHTSTAND_MIN"] == 2
    assert (wheel["PATH_WIDTH"], wheel["TURN_DIAMETER"], wheel["TURN_NEAR"]) == (0.9, 1.5, 0.5)
    # the turning circle must be next to a bed: having a bed earns the small existence credit
    assert "def check_has_bed(scene)" in PROGRAMS["wheelchair"].code and wheel["W_HAS_BED"] == 0.5
    assert "farsighted" in PROGRAMS["tv_from_bed"].reasoning and "4k" in PROGRAMS["tv_from_bed"].reasoning


def test_programs_run_on_odd_scenes():
    layouts = random_layouts(6, seed=2) + [make_layout([box("ceiling_lamp", 2, 1.5, 0.3, 0.3, y0=2.4, hy=0.1)])]
    for p in PROGRAMS.values():
        run(p.code, layouts)


def test_programs_load_and_score_in_the_sandbox():
    batch = SceneBatch.from_layouts(generate_layouts("bedroom", 8, seed=5), "bedroom")
    with RewardSandbox("bedroom", timeout=60) as sandbox:
        for name, p in PROGRAMS.items():
            loaded = sandbox.load(p.code)
            assert loaded.ok, f"{name}: {loaded.message}"
            scored = sandbox.score(batch)
            assert scored.ok and scored.nonfinite == 0 and scored.values.shape == (8,), f"{name}: {scored.message}"


# --------------------------------------------------------------------------------------------------------
# Alignment with the hand-written checkers, and density
# --------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def procedural():
    return generate_layouts("bedroom", 150, seed=3)


@pytest.mark.parametrize("name", list(TASKS))
def test_aligned_on_procedural_bedrooms(name, procedural):
    acc, rej, area = alignment(name, procedural)
    assert acc > rej + 0.3 and area > 0.95, (acc, rej, area)


@pytest.mark.parametrize("name", list(TASKS))
def test_aligned_on_real_bedrooms(name):
    from iarcs_env.datasets import load_layouts

    layouts = load_layouts(real_file("bedroom_val.json"), "bedroom")
    acc, rej, area = alignment(name, layouts)
    assert acc > rej + 0.3 and area > 0.95, (acc, rej, area)


@pytest.mark.parametrize("name", list(TASKS))
def test_dense_partial_credit(name):
    """Rejected scenes (random rooms with random objects) are not all scored alike: the reward grades
    how close they are."""
    layouts = random_layouts(80, seed=4, max_objects=12)
    accepted = task_results(name, layouts)
    values = run(PROGRAMS[name].code, layouts)[~accepted]
    assert len(np.unique(values.round(3))) >= 10 and values.max() > 0.3


def bed(z=1.0):
    return box("double_bed", 3.0, z, 0.9, 1.0, hy=0.45)  # faces +z, headboard at z - 1.0, top 0.9 m


def scores(name, scenes):
    return run(PROGRAMS[name].code, [make_layout(objects, floor=ROOM) for objects in scenes])


def decreasing(values):
    return bool(np.all(np.diff(values) < -1e-4))


def test_reward_climbs_toward_satisfaction():
    # reach_1m: a wardrobe coming down to 1.0 m
    reach = scores("reach_1m", [[bed(), box("wardrobe", 5.5, 3, 0.3, 0.8, hy=h / 2)] for h in (1.0, 1.3, 1.7, 2.2)])
    assert reach[0] == pytest.approx(1.0) and decreasing(reach)
    # tv_from_bed: a TV stand 3.5 m ahead turning away from the bed
    tv = scores("tv_from_bed", [[bed(), box("tv_stand", 3.0, 4.5, 0.8, 0.25, yaw=math.pi - a, hy=0.25)]
                                for a in (0.0, 0.7, 1.4, 2.2)])
    assert tv[0] == pytest.approx(1.0) and decreasing(tv)
    # study_zone: the chair pulled away from the desk
    desk = box("desk", 3.0, 0.3, 0.6, 0.3, hy=0.38)
    study = scores("study_zone", [[desk, box("chair", 3.0, z, 0.25, 0.25)] for z in (0.9, 1.8, 2.6, 3.5)])
    assert study[0] == pytest.approx(1.0) and decreasing(study)
    # two_nightstands: the right nightstand moved out from the bed's side
    left = box("nightstand", 4.2, 0.25, 0.25, 0.2, hy=0.3)
    stands = scores("two_nightstands", [[bed(), left, box("nightstand", 1.8 - d, 0.25, 0.25, 0.2, hy=0.3)]
                                        for d in (0.0, 0.4, 0.8, 1.4)])
    assert stands[0] == pytest.approx(1.0) and decreasing(stands)
    # wheelchair: a wardrobe moved from the wall into the only free space beside the bed
    small = [(0, 0), (4.2, 0), (4.2, 3.4), (0, 3.4)]
    wheel = run(PROGRAMS["wheelchair"].code, [make_layout([box("double_bed", 1.0, 1.0, 1.0, 1.0, hy=0.45),
                                                           box("wardrobe", x, 1.5, 0.3, 1.0, hy=1.0)], floor=small)
                                              for x in (3.9, 3.3, 2.4)])
    assert wheel[0] == pytest.approx(1.0) and decreasing(wheel)


# --------------------------------------------------------------------------------------------------------
# Vocabulary, unknown words, determinism
# --------------------------------------------------------------------------------------------------------
def test_vocabulary_synonyms_numbers_and_units():
    keys = {c: [k.key for k in read_constraint(c).checks] for c in (
        "two bedside tables on either side of the bed", "2 nightstands on both sides of the bed")}
    assert len(set(map(tuple, keys.values()))) == 1
    plan = read_constraint("A bedroom with at most one wardrobe, a 90 cm clear path and the desk against the wall")
    assert [c.key for c in plan.checks] == ["count_wardrobe", "clear_paths", "desk_against_wall"]
    assert plan.checks[1].params[0].value == pytest.approx(0.9)
    p = PLANNER.synthesize("bedroom", "The sofa facing the TV within 20 degrees, a lamp next to the bed")
    assert program_constants(p.code)["FACING_ANGLE_DEG"] == 20 and p.not_understood == []
    assert check_program(p.code) == []


def test_parallel_to_the_walls_scores_square_furniture_above_turned_furniture():
    plan = read_constraint("All furniture parallel to the walls and the wardrobe against the wall")
    assert [c.key for c in plan.checks] == ["furniture_aligned_with_walls", "wardrobe_against_wall"]
    assert plan.not_understood == []
    p = PLANNER.synthesize("bedroom", "A bedroom with every piece of furniture aligned with the walls")
    assert check_program(p.code) == [] and program_constants(p.code)["ALIGN_ANGLE_DEG"] == 10
    square = make_layout([box("double_bed", 2.0, 1.1, 0.9, 1.0), box("nightstand", 3.3, 0.3, 0.25, 0.25,
                                                                        yaw=math.pi / 2)])
    turned = [make_layout([box("double_bed", 2.0, 1.1, 0.9, 1.0, yaw=math.radians(a)),
                           box("nightstand", 3.3, 0.3, 0.25, 0.25)]) for a in (12, 25, 40)]
    scores = run(p.code, [square, *turned])
    assert scores[0] > 0.99 and scores[0] > scores[1] > scores[2] > scores[3]


#: One constraint per check kind that needs its objects, and the has_<object> checks it must come with.
NEEDS_OBJECTS_PROMPTS = {
    "either_side": ("night tables on either side of the bed", {"has_nightstand", "has_bed"}),
    "side": ("a lamp to the left of the bed", {"has_lamp", "has_bed"}),
    "in_front": ("a chair in front of the desk", {"has_chair", "has_desk"}),
    "view": ("view the TV from the sofa", {"has_tv", "has_sofa"}),
    "facing": ("the sofa facing the TV", {"has_sofa", "has_tv"}),
    "near": ("a lamp next to the bed", {"has_lamp", "has_bed"}),
    "turning": ("a 1.2 m turning circle next to the sofa", {"has_sofa"}),
    "away": ("the desk facing away from the bed", {"has_desk", "has_bed"}),
    "behind": ("a chair behind the desk", {"has_chair", "has_desk"}),
    "between": ("a nightstand between the bed and the wardrobe", {"has_nightstand", "has_bed", "has_wardrobe"}),
}


@pytest.mark.parametrize("kind", NEEDS_OBJECTS)
def test_a_check_that_needs_objects_adds_their_existence(kind):
    """Every object a relation (or a turning circle next to an object) needs gets a has_<object> check of the low
    IMPLIED_WEIGHT, so a policy without that object already earns credit for adding one."""
    prompt, implied = NEEDS_OBJECTS_PROMPTS[kind]
    plan = read_constraint(prompt)
    assert plan.not_understood == [] and [c.kind for c in plan.checks if c.weight > IMPLIED_WEIGHT] == [kind]
    assert {c.key for c in plan.checks if c.kind == "exists" and c.weight == IMPLIED_WEIGHT} == implied
    # the ones an emptier room satisfies, and a turning circle with no object named, need no object
    assert read_constraint("the sofa at least 2 m away from the TV").checks[0].kind not in NEEDS_OBJECTS
    assert [c.key for c in read_constraint("a turning circle of 1.5 m").checks] == ["turning_circle"]


def test_wheelchair_pays_for_adding_the_bed():
    """The turning circle must be next to a bed: a room without one scores higher once a bed stands in it, even
    where the turning circle still fails (the room is too narrow for it) and the paths stay as they were: by the
    bed's own weight, and a little more as the circle's graded credit (the room's largest circle by the bed) starts
    counting."""
    narrow = [(0, 0), (1.4, 0), (1.4, 3.0), (0, 3.0)]
    without, with_bed = run(PROGRAMS["wheelchair"].code, [make_layout([box(label, 0.7, 1.5, 0.5, 0.5, hy=0.3)],
                                                                      floor=narrow)
                                                          for label in ("wardrobe", "single_bed")])
    c = program_constants(PROGRAMS["wheelchair"].code)
    total = c["W_CLEAR_PATHS"] + c["W_TURNING_CIRCLE"] + c["W_HAS_BED"]
    bed_share = c["W_HAS_BED"] / total
    assert bed_share < with_bed - without < bed_share + 0.1 * c["W_TURNING_CIRCLE"] / total, (without, with_bed)


def test_unknown_words_are_reported_not_guessed():
    p = PLANNER.synthesize("bedroom", "a bedroom with a bed and a purple unicorn")
    assert p.not_understood == ["purple unicorn"] and "purple unicorn" in p.reasoning
    assert [line.split(" ")[0] for line in p.decomposition] == ["has_bed"]
    p = PLANNER.synthesize("bedroom", "a cozy bedroom with a desk in front of the window")
    assert "cozy" in p.not_understood and "window" in p.not_understood
    with pytest.raises(ValueError, match="purple unicorn"):
        PLANNER.synthesize("bedroom", "a bedroom with a purple unicorn")
    with pytest.raises(ValueError, match="empty"):
        PLANNER.synthesize("bedroom", "  ")


def test_deterministic():
    again = OfflinePlanner()
    for name, task in TASKS.items():
        assert again.synthesize("bedroom", task.prompt).to_dict() == PROGRAMS[name].to_dict()
    ctx = ReflectionContext(PROGRAMS["study_zone"], 0, {}, [0.01, 0.02, 0.01, 0.01])
    assert PLANNER.reflect(ctx).to_dict() == again.reflect(ctx).to_dict()


def test_feedback_gives_the_conservative_form():
    p = PLANNER.synthesize("bedroom", TASKS["wheelchair"].prompt, feedback="timed out after 10 s")
    assert program_constants(p.code)["PARTIAL_CREDIT"] == 0 and "timed out" in p.notes


# --------------------------------------------------------------------------------------------------------
# Reflection
# --------------------------------------------------------------------------------------------------------
FLAT = {"task": {"values": [0.2, 0.21, 0.2, 0.2], "max": 0.6, "mean": 0.2, "min": 0.0}}


def test_success_trend():
    assert success_trend([0.1])[0] == "unknown"
    assert success_trend([0.02, 0.03, 0.02, 0.02])[0] == "failing"
    assert success_trend([0.02, 0.05, 0.1, 0.16])[0] == "rising"
    assert success_trend([0.3, 0.3, 0.31, 0.3])[0] == "flat"
    assert success_trend([0.5, 0.7])[0] == "high"


def test_failing_reward_gets_a_curriculum_then_a_simplification():
    p0 = PROGRAMS["two_nightstands"]
    history = [0.02, 0.03, 0.02, 0.02]
    p1 = PLANNER.reflect(ReflectionContext(p0, 0, FLAT, history))
    assert p1.code != p0.code and check_program(p1.code) == []
    assert p1.curriculum["parameter"] == "SIDE_GAP" and p1.curriculum["values"][-1] == 0.5
    assert program_constants(p1.code)["SIDE_GAP"] == p1.curriculum["values"][0] > 0.5
    assert "failing" in p1.notes and "Curriculum" in p1.notes
    # one more flat evaluation: too early to judge; two more: simplify (softer terms)
    assert PLANNER.reflect(ReflectionContext(p1, 1, FLAT, history + [0.02])).code == p1.code
    p2 = PLANNER.reflect(ReflectionContext(p1, 1, FLAT, history + [0.02, 0.03, 0.02]))
    c1, c2 = program_constants(p1.code), program_constants(p2.code)
    assert p2.code != p1.code and c2["SIDE_SCALE"] == 2 * c1["SIDE_SCALE"] and "simplify" in p2.notes
    # success climbs and gets high: tighten the curriculum stage by stage, then restore the softness
    history += [0.02, 0.03, 0.02, 0.3, 0.65]
    p3 = PLANNER.reflect(ReflectionContext(p2, 2, FLAT, history))
    assert p3.curriculum["stage"] == 1 and program_constants(p3.code)["SIDE_GAP"] == p3.curriculum["values"][1]
    p4 = PLANNER.reflect(ReflectionContext(p3, 3, FLAT, history + [0.7]))
    p5 = PLANNER.reflect(ReflectionContext(p4, 4, FLAT, history + [0.7, 0.72]))
    assert program_constants(p5.code) == program_constants(p0.code)  # back at the final target, full program
    assert check_program(p5.code) == []


def test_rising_success_keeps_the_program():
    p0 = PROGRAMS["study_zone"]
    p1 = PLANNER.reflect(ReflectionContext(p0, 0, FLAT, [0.02, 0.05, 0.1, 0.16]))
    assert p1.code == p0.code and "rising" in p1.notes and p1.curriculum == {}


def test_sandbox_failures_give_a_safer_program():
    p0 = PROGRAMS["wheelchair"]
    p1 = PLANNER.reflect(ReflectionContext(p0, 0, FLAT, [0.1, 0.3], sandbox_messages=["timed out after 10 s"]))
    assert program_constants(p1.code)["PARTIAL_CREDIT"] == 0 and "timed out" in p1.notes
    assert check_program(p1.code) == []


def failing_reflections(p0, n):
    """n reflections of a reward whose task success stays near zero (two more evaluations before each)."""
    history, out, p = [0.02, 0.03, 0.02, 0.02], [], p0
    for k in range(n):
        p = PLANNER.reflect(ReflectionContext(p, k, FLAT, history))
        out.append(p)
        history = history + [0.02, 0.01]
    return out


def checks_and_weights(code):
    names = set(re.findall(r"^def (check_\w+)\(scene\)", code, flags=re.M))
    weights = {k: v for k, v in program_constants(code).items() if k.startswith("W_")}
    return names, weights


@pytest.mark.parametrize("name", list(TASKS))
def test_failing_reflection_never_drops_a_check(name):
    """However long success stays low, every check (and its weight) stays in the program: a reward without a
    check the constraint requires stops measuring it. Weights only grow, by at most 4x."""
    p0 = PROGRAMS[name]
    checks0, weights0 = checks_and_weights(p0.code)
    assert checks0 and set(weights0) == {"W_" + c[len("check_"):].upper() for c in checks0}
    steps = failing_reflections(p0, 7)
    for p in steps:
        checks, weights = checks_and_weights(p.code)
        assert checks == checks0 and set(weights) == set(weights0), p.notes
        assert all(weights0[k] <= weights[k] <= 4 * weights0[k] for k in weights0), p.notes
        assert check_program(p.code) == [] and "drop the" not in p.notes
    assert steps[-1].code == steps[-2].code and "Reflection: keep." in steps[-1].reasoning
    assert "No check is dropped" in steps[-1].notes
    again = OfflinePlanner()   # deterministic, step by step
    assert again.reflect(ReflectionContext(steps[2], 3, FLAT, [0.02] * 10)).to_dict() == \
        PLANNER.reflect(ReflectionContext(steps[2], 3, FLAT, [0.02] * 10)).to_dict()


def test_emphasis_raises_the_requirement_weights():
    """After the curriculum and the simplification, a still failing reward weighs up the checks that need the
    constraint's objects (the relation, the turning circle, has_bed) up to 4x, keeps the others, then stops."""
    steps = failing_reflections(PROGRAMS["wheelchair"], 5)
    assert [p.reasoning.rsplit(" ", 1)[-1] for p in steps] == \
        ["curriculum.", "simplification.", "emphasis.", "emphasis.", "keep."]
    w = [program_constants(p.code) for p in steps]
    assert [c["W_TURNING_CIRCLE"] for c in w] == [2, 2, 4, 8, 8]
    assert [c["W_CLEAR_PATHS"] for c in w] == [2] * 5      # an emptier room satisfies it: not weighed up
    assert [c["W_HAS_BED"] for c in w] == [0.5, 0.5, 1, 2, 2]  # the bed the turning circle needs
    assert "emphasise" in steps[2].notes and "W_TURNING_CIRCLE 2 -> 4" in steps[2].notes
    assert "cap" in steps[4].notes and steps[4].code == steps[3].code
    assert w[2]["AND_SHARE"] == 0.25 and w[2]["PATH_WIDTH"] == w[1]["PATH_WIDTH"]  # nothing else changes
    assert "turning_circle (weight 4)" in " ".join(steps[2].decomposition)
    # two nightstands: the relation and has_bed weigh up, the count keeps its weight
    steps = failing_reflections(PROGRAMS["two_nightstands"], 5)
    w = [program_constants(p.code) for p in steps]
    assert [c["W_NIGHTSTAND_EITHER_SIDE_OF_BED"] for c in w] == [2, 2, 4, 8, 8]
    assert [c["W_HAS_BED"] for c in w] == [0.5, 0.5, 1, 2, 2]
    assert [c["W_COUNT_NIGHTSTAND"] for c in w] == [1] * 5
    # the reward now pays less for the easy part alone: two nightstands and no bed
    no_bed = [make_layout([box("nightstand", 2.0, 0.25, 0.25, 0.2, hy=0.3),
                           box("nightstand", 4.0, 0.25, 0.25, 0.2, hy=0.3)], floor=ROOM)]
    before, after = run(steps[1].code, no_bed)[0], run(steps[3].code, no_bed)[0]
    assert after < before - 0.1, (before, after)
    # success high again: tightening restores the softness, the emphasis stays
    history = [0.02] * 12 + [0.65, 0.7]
    p = steps[3]
    for k in range(3):
        p = PLANNER.reflect(ReflectionContext(p, 10 + k, FLAT, history + [0.7] * (2 * k)))
    c = program_constants(p.code)
    assert c["AND_SHARE"] == 0.5 and c["SIDE_GAP"] == 0.5 and c["W_NIGHTSTAND_EITHER_SIDE_OF_BED"] == 8


def test_emphasis_that_changes_nothing_keeps_the_program():
    """When every check needs the constraint's objects, weighing them all up leaves the weighted mean as it is:
    the planner says so and keeps the program instead of calling a rescaling a change."""
    steps = failing_reflections(PROGRAMS["tv_from_bed"], 3)
    assert steps[2].code == steps[1].code and "Reflection: keep." in steps[2].reasoning
    assert "weighted mean unchanged" in steps[2].notes and "No check is dropped" in steps[2].notes


def test_a_dropped_check_comes_back():
    """A program of mine that lacks one of the plan's checks (an earlier planner version dropped it) gets it
    back at the next reflection, even when the program would otherwise be kept."""
    prompt = TASKS["wheelchair"].prompt
    plan = read_constraint(prompt)
    plan.checks = [c for c in plan.checks if c.key != "turning_circle"]
    legacy = RewardProposal(**{**PROGRAMS["wheelchair"].to_dict(), "code": render(plan)})
    assert "def check_turning_circle(" not in legacy.code
    p = PLANNER.reflect(ReflectionContext(legacy, 0, FLAT, [0.02, 0.05, 0.1, 0.16]))   # rising: would keep
    assert "def check_turning_circle(" in p.code and "W_TURNING_CIRCLE" in p.code and "turning_circle" in p.notes
    assert p.code == PROGRAMS["wheelchair"].code and check_program(p.code) == []
