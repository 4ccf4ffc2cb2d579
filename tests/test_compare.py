"""``iarcs compare``: pooled changes between ``iarcs evaluate`` reports, with a floor-level bootstrap interval."""

import json

import pytest

from experiments.cli import main
from iarcs_env.compare import compare_reports
from iarcs_env.datasets import save_layouts
from scene_factory import box, make_layout, random_layouts


def evaluate(tmp_path, layouts, name, *extra):
    scenes, report = tmp_path / f"{name}.json", tmp_path / f"{name}_report.json"
    save_layouts(layouts, scenes)
    assert main(["evaluate", "--scenes", str(scenes), "--features", "none", "--out", str(report), *extra]) == 0
    return report


def pairs(n, apart):
    """n bedrooms with a wardrobe and a cabinet; in the first ``apart`` rooms they stand apart, in the others
    they overlap."""
    return [make_layout([box("wardrobe", 1.0, 1.5, 0.5, 0.3), box("cabinet", 2.8 if i < apart else 1.8, 1.5, 0.5, 0.3)],
                        id=f"room_{i}") for i in range(n)]


def test_pooled_values_are_the_reports_own_and_pairs_pool(tmp_path):
    a = evaluate(tmp_path, random_layouts(15, seed=0, max_objects=6), "seed0", "--task", "reach_1m")
    b = evaluate(tmp_path, random_layouts(15, seed=1, max_objects=6), "seed1", "--task", "reach_1m")
    ra, rb = json.loads(a.read_text()), json.loads(b.read_text())
    one = {c.metric: c for c in compare_reports([ra], [ra], n_boot=200)}
    for key in ("Col_obj", "Col_scene", "R_out", "R_reach", "R_walkable"):
        assert one[key].base == pytest.approx(ra[key], abs=1e-6), key
    assert one["task_reach_1m"].base == pytest.approx(ra["task_success_reach_1m"])
    # identical sides: no change, and no spread in the interval
    assert one["Col_obj"].change == 0 and one["Col_obj"].low == 0 and one["Col_obj"].high == 0
    # two pairs pool their counts (not their rates)
    both = {c.metric: c for c in compare_reports([ra, rb], [ra, rb], n_boot=200)}
    ground = ra["n_ground_objects"] + rb["n_ground_objects"]
    colliding = ra["Col_obj"] * ra["n_ground_objects"] + rb["Col_obj"] * rb["n_ground_objects"]
    assert both["Col_obj"].base == pytest.approx(colliding / ground)


def test_a_real_fall_has_an_interval_below_zero(tmp_path, capsys):
    base = evaluate(tmp_path, pairs(40, apart=0), "base")
    run = evaluate(tmp_path, pairs(40, apart=30), "run")
    out = tmp_path / "change.json"
    assert main(["compare", "--base", str(base), "--run", str(run), "--boot", "500", "--out", str(out)]) == 0
    changes = {c["metric"]: c for c in json.loads(out.read_text())["changes"]}
    col = changes["Col_obj"]
    assert col["base"] == 1.0 and col["run"] == pytest.approx(0.25) and col["change"] == pytest.approx(-0.75)
    assert -0.9 < col["low"] <= col["change"] <= col["high"] < -0.6
    assert changes["R_out"]["base"] == 0  # nothing out of bound on either side: no change to speak of
    printed = capsys.readouterr().out
    assert "| Col_obj | 100.00% | 25.00% | -75.0% |" in printed and "| R_out | 0.00% | 0.00% | n/a |" in printed


def test_counts_per_room_show_a_rate_moved_by_its_denominator(tmp_path, capsys):
    """A pendant lamp added to every room lowers R_out by a third while the wardrobe stays through the wall:
    the per-room counts show it (out of bound unchanged, objects up, ground objects unchanged)."""
    wall = [box("wardrobe", 0.2, 1.5, 0.5, 0.3), box("cabinet", 2.8, 1.5, 0.5, 0.3)]  # the wardrobe pokes out
    lamp = ("pendant_lamp", (2.0, 2.5, 1.5), (0.2, 0.2, 0.2), 0.0)
    base = evaluate(tmp_path, [make_layout(wall, id=f"room_{i}") for i in range(20)], "base")
    run = evaluate(tmp_path, [make_layout(wall + [lamp], id=f"room_{i}") for i in range(20)], "run")
    assert main(["compare", "--base", str(base), "--run", str(run), "--boot", "200"]) == 0
    printed = capsys.readouterr().out
    assert "| R_out | 50.00% | 33.33% | -33.3% |" in printed
    assert "| out_of_bound / room | 1.000 | 1.000 | +0.0% |" in printed
    assert "| objects / room | 2.000 | 3.000 | +50.0% |" in printed
    assert "| ground_objects / room | 2.000 | 2.000 | +0.0% |" in printed


def test_user_errors_are_clear(tmp_path, capsys):
    base = evaluate(tmp_path, pairs(4, apart=0), "base")
    other = evaluate(tmp_path, pairs(5, apart=0), "other")
    old = tmp_path / "old_report.json"
    report = json.loads(base.read_text())
    for scene in report["per_scene"]:
        del scene["ground_objects"]
    old.write_text(json.dumps(report))
    cases = [
        (["--base", str(base), str(base), "--run", str(base)], "pair every run report with a base report"),
        (["--base", str(base), "--run", str(other)], "does not hold the same scenes"),
        (["--base", str(old), "--run", str(base)], "evaluate its scenes again"),
        (["--base", str(tmp_path / "base.json"), "--run", str(base)], "not an `iarcs evaluate` report"),
        (["--base", str(tmp_path / "missing.json"), "--run", str(base)], "does not exist"),
        (["--base", str(base), "--run", str(base), "--boot", "10"], "--boot must be at least 100"),
    ]
    for argv, message in cases:
        assert main(["compare", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)


def test_relations_pool_over_all_rooms_and_given_their_objects(tmp_path, capsys):
    """Each relation of `iarcs evaluate`'s Relations table is compared over all rooms and over the rooms holding
    its objects: a bed with two nightstands flanking its head (holds), the same nightstands at its foot (the objects
    without the relation), a bed alone (neither)."""
    bed = box("double_bed", 2.0, 1.05, 0.8, 1.0)  # x from 1.2 to 2.8, its head against the wall at z = 0.05
    head = [box("nightstand", 3.05, 0.5, 0.2, 0.2), box("nightstand", 0.95, 0.5, 0.2, 0.2)]
    foot = [box("nightstand", 3.05, 2.6, 0.2, 0.2), box("nightstand", 0.95, 2.6, 0.2, 0.2)]
    placed = {"head": head, "foot": foot, "alone": []}
    rooms = lambda kinds: [make_layout([bed] + placed[k], id=f"room_{i}") for i, k in enumerate(kinds)]  # noqa: E731
    base = evaluate(tmp_path, rooms(["head"] * 2 + ["foot"] * 6 + ["alone"] * 2), "base")
    run = evaluate(tmp_path, rooms(["head"] * 6 + ["foot"] * 2 + ["alone"] * 2), "run")
    changes = {c.metric: c for c in compare_reports([json.loads(base.read_text())], [json.loads(run.read_text())],
                                                     n_boot=200)}
    over_all, given = changes["relation_two_nightstands"], changes["relation_two_nightstands given its objects"]
    assert (over_all.base, over_all.run, over_all.change) == pytest.approx((0.2, 0.6, 2.0))
    assert (given.base, given.run) == pytest.approx((0.25, 0.75))
    assert "relation_tv_from_bed" in changes and changes["relation_tv_from_bed"].base == 0  # no TV stand anywhere
    assert main(["compare", "--base", str(base), "--run", str(run), "--boot", "200"]) == 0
    assert "| relation_two_nightstands given its objects | 25.00% | 75.00% | +200.0% |" in capsys.readouterr().out
