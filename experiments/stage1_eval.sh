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
# the run's room type, and its prior (its config's `prior:`), which draws the base samples without the adapter
read -r ROOM PRIOR < <($PY -c "import sys; from agents.train import load_train_config as load; c = load(sys.argv[1]); print(c.room, c.prior)" "$RUN/config.yaml")
# 500 procedural rooms with a seed used neither by the prior (0) nor by RL training (1000): held-out floors
[ -f "$OUT/floors.json" ] || $IARCS data generate --room "$ROOM" --num-scenes 500 --seed 777 --out "$OUT/floors.json"
BASE_CHECKPOINT=(); [ "$PRIOR" = default ] || BASE_CHECKPOINT=(--checkpoint "$PRIOR")
BASE_REPORTS=(); RUN_REPORTS=()
for SEED in $SEEDS; do
  $IARCS sample --room "$ROOM" --floors "$OUT/floors.json" --num-scenes 500 --seed "$SEED" "${BASE_CHECKPOINT[@]}" --out "$OUT/base_s$SEED.json"
  $IARCS sample --room "$ROOM" --floors "$OUT/floors.json" --num-scenes 500 --seed "$SEED" --checkpoint "$RUN" --out "$OUT/stage1_s$SEED.json"
  $IARCS evaluate --scenes "$OUT/base_s$SEED.json" --features none --name "prior (base), seed $SEED" --out "$OUT/base_s${SEED}_report.json"
  # --reference: the class-frequency KL to the prior's own samples
  $IARCS evaluate --scenes "$OUT/stage1_s$SEED.json" --reference "$OUT/base_s$SEED.json" --features none \
    --name "stage 1 (LoRA), seed $SEED" --out "$OUT/stage1_s${SEED}_report.json"
  BASE_REPORTS+=("$OUT/base_s${SEED}_report.json"); RUN_REPORTS+=("$OUT/stage1_s${SEED}_report.json")
done
$IARCS compare --base "${BASE_REPORTS[@]}" --run "${RUN_REPORTS[@]}" --out "$OUT/change.json"
# contents over all seeds: class-frequency KL to the prior's samples, objects a room, bedrooms with a bed
$PY - "$OUT" $SEEDS <<'PY'
import sys
from iarcs_env.datasets import load_layouts
from iarcs_env.metrics import class_kl, footprint_change
from iarcs_env.relations import BEDS
out, seeds = sys.argv[1], sys.argv[2:]
base, run = ([lay for s in seeds for lay in load_layouts(f"{out}/{name}_s{s}.json")] for name in ("base", "stage1"))
print(f"\nseeds {' '.join(seeds)} pooled: class KL to the prior's samples {class_kl(base, run):.3f}")
change = footprint_change(base, run)  # stage 1 can shrink the beds to clear walls and nightstands
print(f"footprints against the prior's objects of the same classes {100 * change['all']:+.1f}% (geometric mean; "
      + ", ".join(f"{c} {100 * v:+.1f}%" for c, v in list(change["by_class"].items())[:3]) + ")")
for name, lays in (("prior", base), ("stage 1", run)):
    beds = sum(any(label in BEDS for label in lay.labels) for lay in lays) / len(lays)
    print(f"{name}: {sum(len(lay) for lay in lays) / len(lays):.2f} objects a room"
          + (f", a bed in {100 * beds:.1f}% of the rooms" if lays[0].room_type == "bedroom" else ""))
PY
# what the adapter added or removed, class by class (beds are the class most at risk), first seed
FIRST=${SEEDS%% *}
$PY research/class_counts.py "prior=$OUT/base_s$FIRST.json" "stage 1=$OUT/stage1_s$FIRST.json" --out-of-bound --sizes 0.1
