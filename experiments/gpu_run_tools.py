"""The Python steps of ``experiments/gpu_run.sh`` (docs/gpu.md): which carried wheels to install, the prior's
export, the evaluation figures that ``iarcs evaluate`` does not give (object-count TVD and class KL of the
fidelity targets, the reference's own figures, the bed ablation), ``eval.json``, ``bench.json`` and
``report.md``. Each is one sub-command, run by the script under its own time limit::

    python3 experiments/gpu_run_tools.py missing-wheels .whl
    python3 experiments/gpu_run_tools.py export --state RUN/train_state.pt --dest prior_fp16.pt
    python3 experiments/gpu_run_tools.py figures --samples S.json --reference floors.json --out figures.json
    python3 experiments/gpu_run_tools.py bed-ablation --prior P.pt --reference floors.json --out bed.json
    python3 experiments/gpu_run_tools.py bench-json --work WORK --out OUT/bench.json
    python3 experiments/gpu_run_tools.py eval-json --work WORK --out OUT/eval.json
    python3 experiments/gpu_run_tools.py report --work WORK --out OUT/report.md

The work folder's layout is the script's (``steps.tsv``, ``commands.txt``, ``plan.txt``, ``machine.txt``,
``run/``, ``eval/{shipped,trained}/``). ``missing-wheels``, the JSON files and the report import no torch, so
that they take well under a second. Run from the repository root (``python3 -m experiments.cli`` is the CLI).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: The fidelity targets a prior must keep (docs/gpu.md, "Committing a returned prior").
CLASS_KL_MAX = 0.05
COUNT_TVD_MAX = 0.15
POINTS_MAX = 0.10  # Col_obj and R_out within 10 points of the data's
#: The figures of the side-by-side table: (key, label, format).
FIGURES = [("Col_obj", "Col_obj", "pct"), ("Col_scene", "Col_scene", "pct"), ("R_out", "R_out", "pct"),
           ("R_off_floor", "R_off_floor", "pct"), ("R_reach", "R_reach", "pct"), ("R_walkable", "R_walkable", "f3"),
           ("mean_objects", "objects / room", "f2"), ("class_kl_realism", "class KL (eps 1e-3)", "f4"),
           ("count_tvd", "object-count TVD", "f3"), ("beds_tvd", "beds-per-room TVD", "f3"),
           ("KL_class", "KL_class (eps 1e-6)", "f4"),
           ("count_distance", "count EMD", "f3"), ("FID", "FID", "f2"), ("KID", "KID x 1000", "kid"),
           ("SCA", "SCA", "pct")]
PRIORS = ("shipped", "trained")
BOOTSTRAP = 2000


# ------------------------------------------------------------------------------------------------------------
# steps that run torch
# ------------------------------------------------------------------------------------------------------------
def missing_wheels(folder: str) -> list[str]:
    """The wheels of ``folder`` whose distribution is not installed (by name; any installed version counts)."""
    import importlib.metadata as md

    out = []
    for wheel in sorted(Path(folder).glob("*.whl")):
        name = wheel.name.split("-")[0]
        try:
            md.version(name)
        except md.PackageNotFoundError:
            out.append(str(wheel))
    return out


def export(state: str, dest: str) -> dict:
    """The EMA weights of a pretraining state as the float16 prior (as shipped); its step and size."""
    from agents.pretrain import export_prior
    import torch

    path = export_prior(state, dest, half=True)
    saved = torch.load(path, map_location="cpu", weights_only=True)
    return {"prior": str(path), "step": saved["meta"].get("step"), "bytes": path.stat().st_size,
            "dtypes": sorted({str(v.dtype) for v in saved["state_dict"].values()})}


def figures(samples: str, reference: str) -> dict:
    """The fidelity figures ``iarcs evaluate`` does not report: object-count (and, of bedrooms, beds-per-room) TVD
    and class KL (eps 1e-3) of ``iarcs_env.datasets.realism`` (the targets' figures), and the reference's own metrics."""
    from iarcs_env.datasets import load_layouts
    from iarcs_env.datasets.realism import class_kl, count_tvd
    from iarcs_env.metrics import evaluate_layouts
    from iarcs_env.relations import BEDS

    gen, ref = load_layouts(samples), load_layouts(reference)
    ref = ref[:len(gen)]
    out = {"count_tvd": count_tvd(ref, gen), "class_kl_realism": class_kl(ref, gen), "reference": evaluate_layouts(ref)}
    if ref and ref[0].room_type == "bedroom":
        out["beds_tvd"] = count_tvd(ref, gen, BEDS)
    return out


def bed_ablation(prior_path: str, reference: str, device: str, timesteps=(50, 100, 200)) -> dict:
    """:func:`agents.bed_ablation.bed_ablation`'s figures for the prior on the reference rooms (one bed, a
    nightstand)."""
    import torch

    from agents.bed_ablation import bed_ablation as measure
    from agents.config import resolve_device
    from agents.denoiser import ScenePrior
    from iarcs_env.datasets import load_layouts

    torch.set_num_threads(max(1, min(8, torch.get_num_threads())))
    prior = ScenePrior.load(prior_path).to(resolve_device(device))
    rooms = [lay for lay in load_layouts(reference, "bedroom") if len(lay) <= prior.num_slots]
    return {"rooms": len(rooms), "timesteps": list(timesteps),
            "figures": {str(t): f for t, f in measure(prior, rooms, timesteps).items()}}


# ------------------------------------------------------------------------------------------------------------
# the work folder (no torch from here on)
# ------------------------------------------------------------------------------------------------------------
def read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def read_plan(work: Path) -> dict:
    plan = {}
    if (work / "plan.txt").exists():
        for line in (work / "plan.txt").read_text().splitlines():
            if "=" in line:
                k, v = line.split("=", 1)
                plan[k.strip()] = v.strip()
    return plan


def read_steps(work: Path) -> list[dict]:
    rows = []
    if (work / "steps.tsv").exists():
        for line in (work / "steps.tsv").read_text().splitlines():
            parts = line.split("\t")
            if len(parts) >= 5:
                rows.append({"step": parts[0], "status": parts[1], "seconds": float(parts[2]),
                             "limit_s": parts[3], "rc": parts[4], "log": parts[5] if len(parts) > 5 else None})
    return rows


def step_row(work: Path, name: str) -> dict | None:
    return next((r for r in read_steps(work) if r["step"] == name), None)


def tail(path: Path, chars: int = 3000) -> str:
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return ""
    text = re.sub(r"[^\n]*\r", "", text)  # progress bars: the last state of each line
    return text[-chars:]


def bench_json(work: Path) -> dict:
    """``bench.json``: the benchmark's rows, or what its log says when it wrote none (failed, timed out)."""
    raw = read_json(work / "bench_raw.json")
    row = step_row(work, "benchmark") or {"status": "not run"}
    out = {"status": row["status"], "seconds": row.get("seconds"), "command": command_of(work, "benchmark"),
           "rows": raw.get("rows", []) if isinstance(raw, dict) else []}
    if not out["rows"]:
        out["log_tail"] = tail(work / "bench.log")
        out["rows_printed"] = [l for l in tail(work / "bench.log", 20000).splitlines() if " rooms/s" in l]
    return out


def load_prior_eval(work: Path, name: str) -> dict | None:
    """One prior's evaluation: ``iarcs evaluate``'s report (without ``per_scene``), the extra figures, the bed
    ablation; None when the evaluation did not run."""
    folder = work / "eval" / name
    report = read_json(folder / "iarcs.json")
    extra = read_json(folder / "figures.json")
    bed = read_json(folder / "bed_ablation.json")
    if report is None and extra is None and bed is None:
        return None
    out = {k: v for k, v in (report or {}).items() if k not in ("per_scene", "command")}
    if extra:
        out.update({k: v for k, v in extra.items() if k != "reference"})
    if bed:
        out["bed_ablation"] = bed
    out["prior"] = (read_plan(work).get(f"{name}_prior") or "").replace(str(work) + "/", "")
    return out


def scene_flags(work: Path, name: str) -> tuple[list[str], dict[str, list[bool]]] | None:
    """(scene ids, per relation whether it holds in each scene) from ``iarcs evaluate``'s ``per_scene``."""
    report = read_json(work / "eval" / name / "iarcs.json")
    if not report or "per_scene" not in report or "relations" not in report:
        return None
    names = list(report["relations"])
    scenes = report["per_scene"]
    return [s["id"] for s in scenes], {r: [bool(s.get("relations", {}).get(r, False)) for s in scenes] for r in names}


def relation_comparison(work: Path, reference_rates: dict) -> dict | None:
    """The trained prior against the shipped one on the same floors: per relation the difference of the rates
    over all rooms, and of the mean relation recall, each with a 90% interval of a paired bootstrap over the
    floors (the same resampled floors for both priors; the data's rates held fixed)."""
    import random

    a, b = scene_flags(work, "trained"), scene_flags(work, "shipped")
    if a is None or b is None or len(a[0]) != len(b[0]) or not a[0]:
        return None
    n = len(a[0])
    names = [r for r in a[1] if r in b[1]]
    recallable = [r for r in names if (reference_rates.get(r) or 0) > 0]
    rng = random.Random(0)

    def stats(idx):
        d = {r: (sum(a[1][r][i] for i in idx) - sum(b[1][r][i] for i in idx)) / len(idx) for r in names}
        d["mean_recall"] = (sum(d[r] / reference_rates[r] for r in recallable) / len(recallable)) if recallable else 0.0
        return d

    point = stats(range(n))
    draws = [stats([rng.randrange(n) for _ in range(n)]) for _ in range(BOOTSTRAP)]
    out = {}
    for key in [*names, "mean_recall"]:
        values = sorted(d[key] for d in draws)
        out[key] = {"difference": point[key], "interval_90": [values[int(0.05 * len(values))],
                                                              values[int(0.95 * len(values)) - 1]]}
    out["what"] = ("trained minus shipped, on the same floors: rate over all rooms per relation; mean over the "
                   "relations of recall (rate / the data's rate); 90% paired bootstrap intervals over the floors")
    return out


def targets(row: dict, reference: dict) -> dict:
    """Which fidelity targets ``row`` meets against the data's figures (None: a figure is missing)."""
    def check(fn, *keys):
        if any(row.get(k) is None for k in keys) or any(reference.get(k) is None for k in keys if k[0].isupper()):
            return None
        return bool(fn())

    return {
        f"class KL (eps 1e-3) <= {CLASS_KL_MAX}": check(lambda: row["class_kl_realism"] <= CLASS_KL_MAX,
                                                       "class_kl_realism"),
        f"object-count TVD <= {COUNT_TVD_MAX}": check(lambda: row["count_tvd"] <= COUNT_TVD_MAX, "count_tvd"),
        "Col_obj within 10 points of the data's": check(
            lambda: abs(row["Col_obj"] - reference["Col_obj"]) <= POINTS_MAX + 1e-12, "Col_obj"),
        "R_out within 10 points of the data's and not above it": check(
            lambda: abs(row["R_out"] - reference["R_out"]) <= POINTS_MAX + 1e-12 and row["R_out"] <= reference["R_out"],
            "R_out"),
    }


def eval_json(work: Path) -> dict:
    """``eval.json``: the data's figures, the shipped prior's and the trained prior's side by side, on the same
    held-out floors, the targets and the relation comparison."""
    plan = read_plan(work)
    priors = {name: load_prior_eval(work, name) for name in PRIORS}
    reference = {}
    for name in PRIORS:
        extra = read_json(work / "eval" / name / "figures.json")
        if extra and "reference" in extra:
            reference = extra["reference"]
            break
    rates = {}
    for name in PRIORS:
        rel = (priors[name] or {}).get("relations") or {}
        for r, v in rel.items():
            if isinstance(v, dict) and v.get("reference"):
                rates[r] = v["reference"]
    reference["relations"] = rates
    floors = int(plan.get("eval_floors", 0) or 0)
    out = {
        "floors": {"count": floors, "asked": int(plan.get("eval_floors_asked", floors) or floors),
                   "reduced": plan.get("eval_note") or None,
                   "source": f"iarcs data generate --room {plan.get('room', 'bedroom')} --num-scenes N --seed 777 "
                             "(held-out procedural rooms)"},
        "sampler": {"ddim_steps": 20, "eta": 1.0, "seed": 0},
        "reference": reference,
        "shipped": priors["shipped"] or {"status": (step_row(work, "shipped: sample") or {}).get("status", "not run")},
        "trained": priors["trained"] or {"status": (step_row(work, "trained: sample") or {}).get("status", "not run")},
    }
    for name in PRIORS:
        if priors[name] and reference:
            out[name]["targets"] = targets(priors[name], reference)
    out["relations_trained_vs_shipped"] = relation_comparison(work, {r: v.get("rate") for r, v in rates.items()})
    out["commands"] = [l for l in (work / "commands.txt").read_text().splitlines()
                       if l.split(":")[0] in ("floors", "shipped", "trained")] if (work / "commands.txt").exists() else []
    return out


# ------------------------------------------------------------------------------------------------------------
# report.md
# ------------------------------------------------------------------------------------------------------------
def fmt(value, kind: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if kind == "pct":
        return f"{100 * value:.1f}%"
    if kind == "kid":
        return f"{1000 * value:.2f}"
    return f"{value:.{kind[1]}f}"


def command_of(work: Path, step: str) -> str | None:
    if not (work / "commands.txt").exists():
        return None
    for line in (work / "commands.txt").read_text().splitlines():
        if line.startswith(step + ": "):
            return line[len(step) + 2:]
    return None


def metrics_rows(work: Path) -> list[dict]:
    from agents.config import read_jsonl

    path = work / "run" / "metrics.jsonl"
    return read_jsonl(path, warn=lambda message: None) if path.exists() else []


def run_config(work: Path) -> dict:
    try:
        import yaml

        return yaml.safe_load((work / "run" / "config.yaml").read_text()) or {}
    except Exception:  # noqa: BLE001 - no config written (the run failed early) or no yaml
        return {}


def training_summary(work: Path) -> dict:
    """Steps, rooms seen, minutes, steps/s and rooms/s (overall and between the first and last logged steps,
    i.e. without the data and compile time), final losses, from the run folder and its log."""
    rows, cfg = metrics_rows(work), run_config(work)
    step = step_row(work, "train")
    exported = read_json(work / "export.json") or {}
    out = {"status": step["status"] if step else "not run", "wall_s": step["seconds"] if step else None,
           "batch_size": cfg.get("batch_size"), "config": read_plan(work).get("config")}
    if rows:
        last = rows[-1]
        steps = int(exported.get("step") or last["step"])
        out.update(steps=steps, last_logged_step=last["step"], loop_s=last.get("seconds"))
        if cfg.get("batch_size"):
            out["rooms_seen"] = steps * int(cfg["batch_size"])
        if out["wall_s"]:
            out["steps_per_s"] = steps / out["wall_s"]
        first = rows[0]
        if last["step"] > first["step"] and last.get("seconds", 0) > first.get("seconds", 0):
            out["steady_steps_per_s"] = (last["step"] - first["step"]) / (last["seconds"] - first["seconds"])
            if cfg.get("batch_size"):
                out["steady_rooms_per_s"] = out["steady_steps_per_s"] * int(cfg["batch_size"])
        out["final"] = {k: last.get(k) for k in ("loss", "loss_avg", "lr")}
        val = [r for r in rows if "val_loss_ema" in r]
        if val:
            out["final"].update(val_loss_ema=val[-1]["val_loss_ema"], train_rooms_loss_ema=val[-1].get("train_rooms_loss_ema"),
                                val_step=val[-1]["step"])
            out["first_val"] = {"step": val[0]["step"], "val_loss_ema": val[0]["val_loss_ema"],
                                "train_rooms_loss_ema": val[0].get("train_rooms_loss_ema")}
    log = tail(work / "train.log", 200000)
    notes = [l.strip() for l in log.splitlines()
             if re.search(r"torch\.compile|generated [\d,]+ rooms|read [\d,]+ training|initialised from|cached at|"
                          r"time budget is spent|^step \d+|training on|dropped|Error|error", l)]
    out["log_lines"] = notes[-14:]
    out["exported"] = exported or None
    return out


def markdown_report(work: Path) -> str:
    plan, steps = read_plan(work), read_steps(work)
    L = ["# GPU run report", ""]
    L += [f"- started {plan.get('started', '?')}; budget {plan.get('minutes', '?')} min ({plan.get('budget_s', '?')} s); "
          f"the run took {plan.get('elapsed_s', '(still running)')} s" + (" (within budget)" if plan.get("elapsed_s")
          and float(plan["elapsed_s"]) <= float(plan.get("budget_s", 0)) + 30 else ""),
          f"- device: {plan.get('device', '?')}; config `{plan.get('config', '?')}`"
          + (f"; continued from `{plan['continue_from']}`" if plan.get("continue_from") else ""), ""]
    L += ["## Machine", "", "```", (work / "machine.txt").read_text().strip() if (work / "machine.txt").exists()
          else "(not recorded)", "```", ""]

    L += ["## Steps", "", "| step | status | seconds | limit (s) |", "|---|---|---:|---:|"]
    L += [f"| {r['step']} | {r['status']} | {r['seconds']:.1f} | {r['limit_s']} |" for r in steps]
    L += ["", "Plan: " + ", ".join(f"{k} {plan[k]}" for k in ("tests_timeout_s", "bench_timeout_s", "train_window_s",
                                                             "train_budget_s", "eval_reserve_s", "eval_floors")
                                   if k in plan) + "."]
    failed = [r for r in steps if r["log"] and not r["status"].startswith(("ok", "skipped"))]
    for r in failed:  # the work folder is gone after the run: what each failed step said
        L += ["", f"`{r['step']}` {r['status']}; the end of its log:", "", "```",
              tail(Path(r["log"]), 1500).strip()[-1500:] or "(empty)", "```"]
    if plan.get("eval_note"):
        L += ["", f"**Evaluation on fewer floors:** {plan['eval_note']}"]
    if plan.get("install"):
        L += ["", f"Packages installed from the wheel folder: {plan['install']}"]
    L += [""]

    tests = tail(work / "tests.log", 400000)
    summary = [l for l in tests.splitlines() if re.search(r"(passed|failed|skipped|error|no tests ran).* in [\d.]+s", l)]
    failed = [l for l in tests.splitlines() if re.match(r"^(FAILED|ERROR) ", l)]
    L += ["## CUDA tests", "", f"`{command_of(work, 'tests') or '(not run)'}`: "
          + (summary[-1].strip("= ") if summary else f"no summary line ({(step_row(work, 'tests') or {}).get('status', 'not run')})")]
    L += [f"- {l}" for l in failed[:20]] + ["", "Full output: tests.log.", ""]

    bench = bench_json(work)
    L += ["## Pretraining benchmark", "", f"`{bench['command'] or '(not run)'}`: {bench['status']}", ""]
    if bench["rows"]:
        L += ["| device | preset | batch | compiled | rooms/s | MFLOP / room | share of the matmul rate | shares | "
              "kernels / step | GPU busy, queued (ms / step) |", "|---|---|---:|---|---:|---:|---:|---|---:|---|"]
        for r in bench["rows"]:
            shares = ", ".join(f"{k} {v:.0%}" for k, v in (r.get("shares") or {}).items())
            launches = (f"{r['kernels_per_step']:,.0f} | {r['gpu_busy_ms']:.1f}, {r['host_ms']:.1f}" if "host_ms" in r
                        else "– | –")
            L.append(f"| {r['device']} {r.get('precision', '')} | {r['preset']} | {r['batch']} | "
                     f"{'yes' if r['compile'] else 'no'} | "
                     f"{r['rooms_per_s']:,.0f} | {r['flops_per_room'] / 1e6:.1f} | {r['fraction']:.1%} | {shares} | "
                     f"{launches} |")
    elif bench.get("rows_printed"):
        L += ["(no JSON written; rows the benchmark printed:)", "", "```", *bench["rows_printed"], "```"]
    L += [""]

    t = training_summary(work)
    L += ["## Training", "", f"`{command_of(work, 'train') or '(not run)'}`: {t['status']}", ""]
    if t.get("steps") is not None:
        L += [f"- steps: {t['steps']:,} of batch {t['batch_size']}: **{t.get('rooms_seen', 0):,} rooms seen** in "
              f"{(t['wall_s'] or 0) / 60:.2f} min (the step's wall time, with start-up, data and compile; the loop "
              f"{(t.get('loop_s') or 0) / 60:.2f} min)",
              f"- speed: {t.get('steps_per_s', 0):.2f} steps/s overall, "
              f"{t.get('steady_steps_per_s', float('nan')):.2f} steps/s = "
              f"{t.get('steady_rooms_per_s', float('nan')):,.0f} rooms/s between the first and last logged steps"]
        f = t.get("final") or {}
        L.append("- final losses: training " + fmt(f.get("loss"), "f4") + " (running mean " + fmt(f.get("loss_avg"), "f4")
                 + "), EMA validation " + fmt(f.get("val_loss_ema"), "f4") + ", EMA on as many training rooms "
                 + fmt(f.get("train_rooms_loss_ema"), "f4") + (f" (step {f['val_step']})" if f.get("val_step") else ""))
        if t.get("first_val"):
            v = t["first_val"]
            L.append(f"- first validation (step {v['step']}): EMA validation {fmt(v['val_loss_ema'], 'f4')}, training "
                     f"rooms {fmt(v.get('train_rooms_loss_ema'), 'f4')}")
        if t.get("exported"):
            e = t["exported"]
            L.append(f"- exported: prior_fp16.pt, step {e.get('step')}, {e.get('bytes', 0) / 1e6:.1f} MB, "
                     f"{', '.join(e.get('dtypes', []))}")
        rows = [r for r in metrics_rows(work) if "val_loss_ema" in r]
        if rows:
            every = max(1, math.ceil(len(rows) / 15))
            rows = rows[::every] + ([rows[-1]] if (len(rows) - 1) % every else [])
            L += ["", "| step | seconds | loss (running) | EMA val. loss | EMA train-rooms loss | lr |",
                  "|---:|---:|---:|---:|---:|---:|"]
            L += [f"| {r['step']} | {r.get('seconds', 0):.0f} | {fmt(r.get('loss_avg'), 'f4')} | "
                  f"{fmt(r.get('val_loss_ema'), 'f4')} | {fmt(r.get('train_rooms_loss_ema'), 'f4')} | {r.get('lr', 0):.2e} |"
                  for r in rows]
    if t["log_lines"]:
        L += ["", "Log:", "", "```", *t["log_lines"], "```"]
    L += [""]

    ev = eval_json(work)
    L += ["## Evaluation", "", f"{ev['floors']['count']} held-out floors (`iarcs data generate --room "
          f"{plan.get('room', 'bedroom')} --num-scenes {ev['floors']['count']} --seed 777`), one scene per floor, "
          "20-step DDIM, eta 1, seed 0."
          + (f" **Fewer floors than asked ({ev['floors']['asked']}):** {ev['floors']['reduced']}" if ev["floors"]["reduced"]
             else ""), ""]
    ref, cols = ev["reference"], [n for n in PRIORS if "n_scenes" in ev[n] or "count_tvd" in ev[n]]
    L += ["| figure | data | " + " | ".join(f"{n} prior" for n in cols) + " |", "|---|---:|" + "---:|" * len(cols)]
    for key, label, kind in FIGURES:
        if ref.get(key) is None and all(ev[n].get(key) is None for n in cols):
            continue
        L.append(f"| {label} | {fmt(ref.get(key), kind)} | " + " | ".join(fmt(ev[n].get(key), kind) for n in cols) + " |")
    for n in PRIORS:
        if n not in cols:
            L += ["", f"The {n} prior's evaluation did not run: {ev[n].get('status')}."]
    L += [""]
    rel_names = list(ref.get("relations") or {})
    if rel_names:
        L += ["Relations (rate over all rooms; in brackets: given the co-occurrence, and the recall = rate / the data's):",
              "", "| relation | data | " + " | ".join(f"{n} prior" for n in cols) + " |", "|---|---:|" + "---:|" * len(cols)]
        for r in rel_names:
            d = ref["relations"][r]
            cells = []
            for n in cols:
                v = (ev[n].get("relations") or {}).get(r) or {}
                s = v.get("scenes") or {}
                cells.append(f"{fmt(s.get('rate'), 'pct')} ({fmt(s.get('rate_given_co_occurrence'), 'pct')}; "
                             f"recall {fmt(v.get('recall'), 'f2')})")
            L.append(f"| {r} | {fmt(d.get('rate'), 'pct')} ({fmt(d.get('rate_given_co_occurrence'), 'pct')}) | "
                     + " | ".join(cells) + " |")
        L += [""]
    comp = ev.get("relations_trained_vs_shipped")
    if comp:
        L += ["Trained minus shipped, same floors (90% paired bootstrap interval over the floors):", ""]
        L += [f"- {k}: {v['difference']:+.3f} [{v['interval_90'][0]:+.3f}, {v['interval_90'][1]:+.3f}]"
              + (" (rate over all rooms)" if k != "mean_recall" else " (mean relation recall)")
              for k, v in comp.items() if isinstance(v, dict)]
        L += [""]
    beds = {n: ev[n].get("bed_ablation") for n in cols if ev[n].get("bed_ablation")}
    if beds:
        L += ["Bed ablation (agents/bed_ablation.py on these floors' rooms with one bed and a nightstand: rooms noised "
              "to t and restored in one step with and without the bed, 4 noise draws pooled; medians in m):", "",
              "| prior | t | nightstands kept | error with the bed | error, bed removed | ratio "
              "| moved by removing the bed | the bed's own error | error in the restored bed's frame "
              "| out from the bed's side (quartiles): truth / with bed / without |",
              "|---|---:|---|---:|---:|---:|---:|---:|---:|---|"]
        for n, b in beds.items():
            for t_, f in b["figures"].items():
                q = lambda v: ", ".join(fmt(x, "f2") for x in v)  # noqa: E731
                L.append(f"| {n} | {t_} | {f['kept']} of {f['nightstands'] * f['noise_draws']} | "
                         f"{fmt(f['error_with_bed_m'], 'f3')} | {fmt(f['error_without_bed_m'], 'f3')} | "
                         f"{fmt(f['ratio'], 'f2')} | {fmt(f['moved_by_removing_bed_m'], 'f3')} | "
                         f"{fmt(f['bed_error_m'], 'f3')} | {fmt(f['error_from_restored_bed_m'], 'f3')} | "
                         f"{q(f['out_from_side_truth'])} / {q(f['out_from_side_with_bed'])} / "
                         f"{q(f['out_from_side_without_bed'])} |")
        L += [""]
    for n in cols:
        if ev[n].get("targets"):
            L += [f"Fidelity targets, {n} prior: " + "; ".join(
                f"{k}: {'yes' if ok else ('no' if ok is False else '–')}" for k, ok in ev[n]["targets"].items())]
    L += ["", "Commit the returned prior only as docs/gpu.md says (relations better than the shipped prior's, the "
          "fidelity targets kept).", ""]

    L += ["## Commands", "", "```"]
    L += [(work / "commands.txt").read_text().rstrip() if (work / "commands.txt").exists() else "(none)"]
    L += ["```", ""]
    return "\n".join(L)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("missing-wheels")
    s.add_argument("folder")
    s = sub.add_parser("export")
    s.add_argument("--state", required=True)
    s.add_argument("--dest", required=True)
    s.add_argument("--json", required=True)
    s = sub.add_parser("figures")
    s.add_argument("--samples", required=True)
    s.add_argument("--reference", required=True)
    s.add_argument("--out", required=True)
    s = sub.add_parser("bed-ablation")
    s.add_argument("--prior", required=True)
    s.add_argument("--reference", required=True)
    s.add_argument("--device", default="auto")
    s.add_argument("--out", required=True)
    for name in ("bench-json", "eval-json", "report"):
        s = sub.add_parser(name)
        s.add_argument("--work", required=True)
        s.add_argument("--out", required=True)
    args = p.parse_args(argv)

    def write(path, data):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(f"{path}.tmp")
        tmp.write_text(data if isinstance(data, str) else json.dumps(data, indent=1))
        tmp.replace(path)

    if args.cmd == "missing-wheels":
        print("\n".join(missing_wheels(args.folder)))
    elif args.cmd == "export":
        info = export(args.state, args.dest)
        write(args.json, info)
        print(json.dumps(info))
    elif args.cmd == "figures":
        write(args.out, figures(args.samples, args.reference))
    elif args.cmd == "bed-ablation":
        write(args.out, bed_ablation(args.prior, args.reference, args.device))
    elif args.cmd == "bench-json":
        write(args.out, bench_json(Path(args.work)))
    elif args.cmd == "eval-json":
        write(args.out, eval_json(Path(args.work)))
    else:
        write(args.out, markdown_report(Path(args.work)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
