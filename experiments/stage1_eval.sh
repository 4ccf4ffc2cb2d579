#!/usr/bin/env bash
# Stage-1 effect, measured with `iarcs evaluate` on 500 scenes sampled on the same held-out floor plans
# with and without the adapter, for each sampling seed in SEEDS (default "0 1 2 3"), pooled by `iarcs compare`
# with a 90% bootstrap interval of each change (R_out counts about 45 objects in 1,900 per seed, so one
# seed's figure moves by +-15%).  Usage: [SEEDS="0 1 2 3"] bash experiments/stage1_eval.sh RUN_DIR [OUT_DIR]
set -euo pipefail
RUN=${1:?usage: stage1_eval.sh RUN_DIR [OUT_DIR]}
OUT=${2:-$RUN/eval500}
SEEDS=${SEEDS:-0 1 2 3}
IARCS=${IARCS:-.venv/bin/iarcs}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
# 500 procedural bedrooms with a seed used neither by the prior (0) nor by RL training (1000): held-out floors
[ -f "$OUT/floors.json" ] || $IARCS data generate --room bedroom --num-scenes 500 --seed 777 --out "$OUT/floors.json"
# the base samples come from the run's own prior (its config's `prior:`), without the adapter
PRIOR=$($PY -c "import sys; from agents.train import load_train_config; print(load_train_config(sys.argv[1]).prior)" "$RUN/config.yaml")
BASE_CHECKPOINT=(); [ "$PRIOR" = default ] || BASE_CHECKPOINT=(--checkpoint "$PRIOR")
BASE_REPORTS=(); RUN_REPORTS=()
for SEED in $SEEDS; do
  $IARCS sample --room bedroom --floors "$OUT/floors.json" --num-scenes 500 --seed "$SEED" "${BASE_CHECKPOINT[@]}" --out "$OUT/base_s$SEED.json"
  $IARCS sample --room bedroom --floors "$OUT/floors.json" --num-scenes 500 --seed "$SEED" --checkpoint "$RUN" --out "$OUT/stage1_s$SEED.json"
  $IARCS evaluate --scenes "$OUT/base_s$SEED.json" --features none --name "prior (base), seed $SEED" --out "$OUT/base_s${SEED}_report.json"
  # --reference: the class-frequency KL to the prior's own samples
  $IARCS evaluate --scenes "$OUT/stage1_s$SEED.json" --reference "$OUT/base_s$SEED.json" --features none \
    --name "stage 1 (LoRA), seed $SEED" --out "$OUT/stage1_s${SEED}_report.json"
  BASE_REPORTS+=("$OUT/base_s${SEED}_report.json"); RUN_REPORTS+=("$OUT/stage1_s${SEED}_report.json")
done
$IARCS compare --base "${BASE_REPORTS[@]}" --run "${RUN_REPORTS[@]}" --out "$OUT/change.json"
$PY - "${RUN_REPORTS[@]}" <<'PY'
import json, sys
print("\nclass KL to the prior's samples, per seed:", ", ".join(f"{json.load(open(p))['KL_class']:.4f}" for p in sys.argv[1:]))
PY
# what the adapter added or removed, class by class (beds are the class most at risk), first seed
FIRST=${SEEDS%% *}
$PY benchmarks/class_counts.py "prior=$OUT/base_s$FIRST.json" "stage 1=$OUT/stage1_s$FIRST.json" --out-of-bound --sizes 0.1
