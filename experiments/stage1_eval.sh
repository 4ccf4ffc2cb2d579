#!/usr/bin/env bash
# Stage-1 effect, measured with `iarcs evaluate` on 500 scenes sampled on the same held-out floor plans
# with and without the adapter.  Usage: bash experiments/stage1_eval.sh RUN_DIR [OUT_DIR]
set -euo pipefail
RUN=${1:?usage: stage1_eval.sh RUN_DIR [OUT_DIR]}
OUT=${2:-$RUN/eval500}
IARCS=${IARCS:-.venv/bin/iarcs}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
# 500 procedural bedrooms with a seed used neither by the prior (0) nor by RL training (1000): held-out floors
$IARCS data generate --room bedroom --num-scenes 500 --seed 777 --out "$OUT/floors.json"
# the base samples come from the run's own prior (its config's `prior:`), without the adapter
PRIOR=$($PY -c "import sys; from agents.train import load_train_config; print(load_train_config(sys.argv[1]).prior)" "$RUN/config.yaml")
BASE_CHECKPOINT=(); [ "$PRIOR" = default ] || BASE_CHECKPOINT=(--checkpoint "$PRIOR")
$IARCS sample --room bedroom --floors "$OUT/floors.json" --num-scenes 500 --seed 0 "${BASE_CHECKPOINT[@]}" --out "$OUT/base.json"
$IARCS sample --room bedroom --floors "$OUT/floors.json" --num-scenes 500 --seed 0 --checkpoint "$RUN" --out "$OUT/stage1.json"
$IARCS evaluate --scenes "$OUT/base.json" --reference "$OUT/base.json" --features none --name "prior (base)" --out "$OUT/base_report.json"
$IARCS evaluate --scenes "$OUT/stage1.json" --reference "$OUT/base.json" --features none --name "stage 1 (LoRA)" --out "$OUT/stage1_report.json"
$PY - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
b, s = (json.load(open(f"{out}/{n}_report.json")) for n in ("base", "stage1"))
print("| metric | prior | stage 1 | change |\n|---|---|---|---|")
for k in ("Col_obj", "Col_scene", "R_out", "R_reach", "R_walkable", "R_off_floor", "R_misaligned"):
    print(f"| {k} | {b[k]:.4f} | {s[k]:.4f} | {100 * (s[k] - b[k]) / max(b[k], 1e-9):+.1f}% |")
print(f"| class KL to the prior's samples | – | {s['KL_class']:.4f} | |")
PY
# what the adapter added or removed, class by class (beds are the class most at risk)
$PY benchmarks/class_counts.py "prior=$OUT/base.json" "stage 1=$OUT/stage1.json" --sizes 0.1
