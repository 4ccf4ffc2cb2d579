"""Realism of the embedded procedural generator against real 3D-FRONT layouts.

Run as a script (not an import: torchrl installs a site-packages package called ``benchmarks``)::

    .venv/bin/python benchmarks/bench_realism.py

Generates 500 bedrooms and 500 living rooms (seed 0, flaw_rate 1) and compares them with
``../shared/data/3dfront/{bedroom,livingroom}_val.json`` (skipped with a message when that folder is
absent): object-count TVD (target <= 0.15), class-frequency KL(real || generated) (<= 0.10), median room
area ratio (within 20%), plus the non-rectangular fraction, the flaw rates (Col_obj, Col_scene, R_out)
and generation speed against reading the real JSON file. Figures are defined in
``iarcs_env/datasets/realism.py``. Prints a table, writes ``docs/results/realism.md`` and exits
non-zero when a bedroom or living-room target is missed.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from iarcs_env.datasets.json_format import read_json_layouts  # noqa: E402
from iarcs_env.datasets.procedural import generate_layouts  # noqa: E402
from iarcs_env.datasets.realism import flaw_rates, realism_figures  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "3dfront"
COMMAND = ".venv/bin/python benchmarks/bench_realism.py"
N, SEED = 500, 0
TARGETS = {"count_tvd": 0.15, "class_kl": 0.10, "area_ratio": 0.20}


def measure(room: str) -> dict:
    t0 = time.perf_counter()
    real = read_json_layouts(REAL / f"{room}_val.json")
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    gen = generate_layouts(room, N, seed=SEED, flaw_rate=1.0)
    t_gen = time.perf_counter() - t0
    fig = realism_figures(real, gen)
    fig["gen_scenes_per_s"] = N / t_gen
    fig["read_scenes_per_s"] = len(real) / t_read
    fig["speed_ratio"] = fig["gen_scenes_per_s"] / fig["read_scenes_per_s"]
    fig["flaws_real"] = flaw_rates(real)
    fig["flaws_generated"] = flaw_rates(gen)
    fig["pass"] = {
        "count_tvd": fig["count_tvd"] <= TARGETS["count_tvd"],
        "class_kl": fig["class_kl"] <= TARGETS["class_kl"],
        "area_ratio": abs(fig["area_ratio"] - 1) <= TARGETS["area_ratio"],
    }
    return fig


def table(results: dict) -> str:
    ok = lambda b: "yes" if b else "**no**"  # noqa: E731
    rows = ["| figure | target | " + " | ".join(results) + " |", "|---|---|" + "---|" * len(results)]

    def row(name, target, fmt):
        rows.append(f"| {name} | {target} | " + " | ".join(fmt(f) for f in results.values()) + " |")

    row("object-count TVD", "<= 0.15", lambda f: f"{f['count_tvd']:.3f} ({ok(f['pass']['count_tvd'])})")
    row("class KL(real \\|\\| gen)", "<= 0.10", lambda f: f"{f['class_kl']:.4f} ({ok(f['pass']['class_kl'])})")
    row("median area ratio (gen / real)", "0.8-1.2",
        lambda f: f"{f['area_ratio']:.3f} ({f['median_area_generated']:.1f} / {f['median_area_real']:.1f} m^2; "
                  f"{ok(f['pass']['area_ratio'])})")
    row("mean objects per room (real / gen)", "-", lambda f: f"{f['mean_count_real']:.2f} / {f['mean_count_generated']:.2f}")
    row("non-rectangular fraction (real / gen)", "-", lambda f: f"{f['nonrect_real']:.3f} / {f['nonrect_generated']:.3f}")
    for k in ("Col_obj", "Col_scene", "R_out"):
        row(f"{k} (real / gen)", "-", lambda f, k=k: f"{f['flaws_real'][k]:.3f} / {f['flaws_generated'][k]:.3f}")
    row("generation speed (scenes/s)", "-", lambda f: f"{f['gen_scenes_per_s']:.0f}")
    row("speed vs reading the real JSON", "-",
        lambda f: f"{f['speed_ratio']:.3f}x (read {f['read_scenes_per_s']:.0f} scenes/s)")
    return "\n".join(rows)


def main() -> int:
    if not REAL.is_dir():
        print(f"SKIPPED: real 3D-FRONT layouts not found at {REAL}; nothing to compare against.")
        return 0
    results = {room: measure(room) for room in ("bedroom", "livingroom")}
    text = table(results)
    print(text)
    missed = [f"{room} {k}" for room, f in results.items() for k, v in f["pass"].items() if not v]
    out = ROOT / "docs" / "results" / "realism.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        f"# Realism of the procedural generator\n\n```\n{COMMAND}\n```\n\n"
        f"{N} generated rooms per type (seed {SEED}, flaw_rate 1) against the real 3D-FRONT validation "
        "files (500 rooms each). Figures are defined in `iarcs_env/datasets/realism.py`; the targets apply "
        "to bedrooms and living rooms (the script exits non-zero when one is missed).\n\n"
        f"{text}\n\nTargets: {'all met' if not missed else 'missed: ' + ', '.join(missed)}.\n")
    print(f"\nwrote {out.relative_to(ROOT)}")
    if missed:
        print(f"FAILED targets: {', '.join(missed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
