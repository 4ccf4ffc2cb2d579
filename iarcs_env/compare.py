"""Is a change in the paper's metrics real, or sampling noise? Paired comparison of ``iarcs evaluate``
reports, with a bootstrap confidence interval.

A stage-1 adapter is judged by the relative change of pooled rates such as ``R_out`` between scenes sampled
with and without it on the same floor plans with the same seed. Those rates are ratios of small counts (about
45 out-of-bound objects in 1,900 for the shipped bedroom prior on 500 floors), so one sampling seed's figure
moves by +-15% between seeds. Here several report pairs (one per sampling seed) are pooled and the change gets
an interval:

* every metric is a ratio of per-scene sums, exactly as :func:`iarcs_env.metrics.evaluate_layouts` pools it:
  ``Col_obj`` = colliding / ground objects, ``Col_scene`` = scenes with a collision / scenes, ``R_out`` =
  out-of-bound / all objects, ``R_reach`` = reachable / ground objects, ``R_walkable`` = mean per scene, and
  ``task_<name>`` = scenes passing the checker / scenes (when the reports have ``--task``), and for each of
  the room type's relations (``iarcs evaluate``'s Relations table) ``relation_<name>`` = scenes where it holds /
  scenes, and ``relation_<name> given its objects`` = scenes where it holds / scenes holding the objects it needs (its
  co-occurrence);
* and three counts per room that say what a rate's change is made of: ``out_of_bound / room`` (R_out's
  numerator), ``objects / room`` (its denominator) and ``ground_objects / room`` (Col_obj's; the difference
  is the ceiling and pendant lamps, which never collide and are hardly ever out of bound, so an adapter
  that adds lamps lowers R_out without moving any furniture back onto the floor);
* change = run / base - 1 of the pooled values;
* the interval resamples floor plans (scene ids, with every seed's scenes of a floor kept together, since one
  floor's samples are correlated) with replacement, ``n_boot`` times, and recomputes the change on each
  resample: the 5th and 95th percentiles give the 90% interval.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

#: Metrics compared (the tasks' success rates are added when every report has them).
COMPARED = ("Col_obj", "Col_scene", "R_out", "R_reach", "R_walkable")
#: Suffix of a relation's rate given its co-occurrence (the scenes holding the objects it needs).
GIVEN_OBJECTS = " given its objects"
#: Counts per room (means over scenes), printed as numbers, not percentages.
PER_ROOM = ("out_of_bound / room", "objects / room", "ground_objects / room")


@dataclass
class Change:
    """One metric: pooled base and run values, relative change run / base - 1 and its bootstrap interval."""

    metric: str
    base: float
    run: float
    change: float
    low: float
    high: float


def _terms(scene: dict, metric: str, where: str) -> tuple[float, float]:
    """(numerator, denominator) of ``metric`` for one per-scene record of an ``iarcs evaluate`` report."""
    if "ground_objects" not in scene:
        raise ValueError(f"{where} has no per-scene ground-object counts (written by iarcs evaluate since "
                         "2026-11-26): evaluate its scenes again with `iarcs evaluate`")
    ground = scene["ground_objects"]
    if metric == "Col_obj":
        return len(scene["colliding"]), ground
    if metric == "Col_scene":
        return float(bool(scene["colliding"])), 1.0
    if metric == "R_out":
        return len(scene["out_of_bound"]), scene["objects"]
    if metric == "R_reach":
        return ground - len(scene["unreachable_objects"]), ground
    if metric == "R_walkable":
        return scene["R_walkable"], 1.0
    if metric.startswith("task_"):
        return float(scene["tasks"][metric[5:]]), 1.0
    if metric.startswith("relation_"):  # a scene's record names a relation only where its co-occurrence holds
        name, given_objects = metric[9:].removesuffix(GIVEN_OBJECTS), metric.endswith(GIVEN_OBJECTS)
        relations = scene.get("relations", {})
        return float(relations.get(name, False)), (float(name in relations) if given_objects else 1.0)
    if metric in PER_ROOM:
        key = metric.split(" / ")[0]
        return float(len(scene[key]) if key == "out_of_bound" else scene[key]), 1.0
    raise ValueError(f"unknown metric {metric!r}; choose from {', '.join(COMPARED + PER_ROOM)} or task_<name>")


def _metrics(reports: Sequence[dict]) -> list[str]:
    tasks = [set(s.get("tasks", {})) for r in reports for s in r["per_scene"]]
    common = sorted(set.intersection(*tasks)) if tasks else []
    relations = [set(r.get("relations", {})) for r in reports]
    shared = [n for n in reports[0].get("relations", {}) if all(n in names for names in relations)]
    return (list(COMPARED) + [f"task_{t}" for t in common]
            + [m for n in shared for m in (f"relation_{n}", f"relation_{n}{GIVEN_OBJECTS}")] + list(PER_ROOM))


def _per_floor(reports: Sequence[dict], ids: list[str], metric: str, side: str) -> np.ndarray:
    """(F, 2) numerator and denominator of ``metric`` summed per floor (scene id) over the reports."""
    index = {i: k for k, i in enumerate(ids)}
    out = np.zeros((len(ids), 2))
    for n, report in enumerate(reports):
        for scene in report["per_scene"]:
            out[index[scene["id"]]] += _terms(scene, metric, f"{side} report {n + 1}")
    return out


def compare_reports(base: Sequence[dict], run: Sequence[dict], n_boot: int = 2000, seed: int = 0,
                    metrics: Sequence[str] | None = None) -> list[Change]:
    """Pooled change of each metric from the ``base`` reports to the ``run`` reports (paired by position: the
    k-th run report must hold the same scene ids as the k-th base report, e.g. the same floors and sampling
    seed with and without an adapter), with a floor-level bootstrap interval (see the module docstring)."""
    if not base or len(base) != len(run):
        raise ValueError(f"pair every run report with a base report: got {len(base)} base and {len(run)} run reports")
    for k, (b, r) in enumerate(zip(base, run)):
        for side, rep in (("base", b), ("run", r)):
            if not rep.get("per_scene"):
                raise ValueError(f"{side} report {k + 1} has no per-scene results; write it with `iarcs evaluate`")
        b_ids, r_ids = [s["id"] for s in b["per_scene"]], [s["id"] for s in r["per_scene"]]
        if sorted(b_ids) != sorted(r_ids):
            raise ValueError(f"report pair {k + 1} does not hold the same scenes ({len(b_ids)} base, {len(r_ids)} run"
                             f"{'' if len(b_ids) != len(r_ids) else ', different ids'}): sample both on the same "
                             "floors file with the same --num-scenes")
        if len(set(b_ids)) != len(b_ids):
            raise ValueError(f"base report {k + 1} repeats scene ids; each scene must have its own id")
    ids = sorted({s["id"] for rep in base for s in rep["per_scene"]})
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(ids), (n_boot, len(ids)))
    changes = []
    for metric in metrics or _metrics(list(base) + list(run)):
        b, r = _per_floor(base, ids, metric, "base"), _per_floor(run, ids, metric, "run")
        b_val, r_val = b[:, 0].sum() / max(b[:, 1].sum(), 1e-12), r[:, 0].sum() / max(r[:, 1].sum(), 1e-12)
        bb = b[draws].sum(1)  # (n_boot, 2)
        rb = r[draws].sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            boot = (rb[:, 0] / rb[:, 1]) / (bb[:, 0] / bb[:, 1]) - 1
            change = r_val / b_val - 1 if b_val else float("nan")
        boot = boot[np.isfinite(boot)]
        low, high = np.quantile(boot, [0.05, 0.95]) if boot.size else (float("nan"), float("nan"))
        changes.append(Change(metric, float(b_val), float(r_val), float(change), float(low), float(high)))
    return changes


def changes_table(changes: Sequence[Change], n_scenes: int, n_pairs: int) -> str:
    """Markdown table of :func:`compare_reports`'s result."""
    lines = [f"{n_scenes} scenes a side over {n_pairs} report pair(s); 90% interval: floor-level bootstrap",
             "", "| metric | base | run | change | 90% interval |", "|---|---:|---:|---:|---|"]
    for c in changes:
        as_number = c.metric == "R_walkable" or c.metric in PER_ROOM
        fmt = (lambda v: f"{v:.3f}") if as_number else (lambda v: f"{100 * v:.2f}%")
        if np.isfinite(c.change):
            change, interval = f"{100 * c.change:+.1f}%", f"{100 * c.low:+.1f}% to {100 * c.high:+.1f}%"
        else:  # a base rate of 0
            change, interval = "n/a", "n/a"
        lines.append(f"| {c.metric} | {fmt(c.base)} | {fmt(c.run)} | {change} | {interval} |")
    return "\n".join(lines)
