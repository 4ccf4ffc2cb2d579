#!/usr/bin/env bash
# The one-command GPU run (docs/gpu.md):
#
#   bash experiments/gpu_run.sh OUT_DIR MINUTES
#
# On a bare CUDA machine with PyTorch (and no package index), inside MINUTES of wall time, in order: the CUDA tests
# (tests/test_device.py), the pretraining benchmark on the GPU, the prior of CONFIG's room (the bedroom's by default)
# trained by CONFIG until the deadline (by default the shipped prior continued), then its evaluation on held-out
# floors beside the data's and the shipped prior's figures (the shipped prior is evaluated while the training runs). Every step has a hard time
# limit; a failed step is recorded and the run goes on. It writes under OUT_DIR only:
#
#   prior_fp16.pt  the trained prior, float16 as shipped    eval.json  the evaluation (data / shipped / trained)
#   bench.json     the benchmark's rows                     tests.log  the tests' output
#   report.md      machine, steps, training, evaluation, the exact commands
#
# Settings (environment): CONFIG (default experiments/pretrain_bedroom_gpu_run.yaml), CONTINUE_FROM (a prior or
# run folder for `--continue-from`; the config's init_from otherwise), EVAL_FLOORS (500), DEVICE (auto: cuda when
# torch sees a GPU), PYTHON (python3), WHEELS (.whl: wheels installed where a package is missing), TESTS
# (tests/test_device.py), TESTS_TIMEOUT and BENCH_TIMEOUT (seconds), BENCH_ARGS (the benchmark's options besides
# --device and --json), EVAL_RESERVE (seconds kept for the evaluation; measured defaults below), KEEP_WORK=1 (keep
# the work folder, printed at the start).
set -u
export PYTHONUNBUFFERED=1
export TQDM_MININTERVAL=${TQDM_MININTERVAL:-5}   # progress bars in logs: a line every 5 s, not 10 a second

if [ $# -ne 2 ] || ! awk -v m="$2" 'BEGIN { exit !(m + 0 > 0) }'; then
    echo "usage: $0 OUT_DIR MINUTES   (MINUTES > 0: the whole run's wall time; see docs/gpu.md)" >&2
    exit 2
fi
now_ms() { date +%s%3N; }
T0=$(now_ms)
MINUTES=$2
BUDGET_S=$(awk -v m="$MINUTES" 'BEGIN { printf "%d", m * 60 }')
DEADLINE=$((T0 + BUDGET_S * 1000))
SETTINGS=""   # the settings given in the environment, for the report's commands
for v in PYTHON CONFIG CONTINUE_FROM EVAL_FLOORS DEVICE WHEELS TESTS TESTS_TIMEOUT BENCH_TIMEOUT BENCH_ARGS EVAL_RESERVE; do
    [ -n "${!v:-}" ] && SETTINGS+="$v=$(printf '%q' "${!v}") "
done
REPO=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$1" || exit 2
OUT=$(cd "$1" && pwd)
cd "$REPO" || exit 2
PY=${PYTHON:-python3}
CONFIG=${CONFIG:-experiments/pretrain_bedroom_gpu_run.yaml}
EVAL_FLOORS=${EVAL_FLOORS:-500}
WHEELS=${WHEELS:-.whl}
TESTS=${TESTS:-tests/test_device.py}
WORK=$(mktemp -d "${TMPDIR:-/tmp}/gpu_run.XXXXXX") || exit 2
[ "${KEEP_WORK:-0}" = 1 ] || trap 'rm -rf "$WORK"' EXIT
export IARCS_CACHE_DIR="$WORK/cache"          # the procedural rooms' cache: in the work folder
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"
SAFETY_S=12                                    # the last eval-json and report, and slack
OUTPUTS="prior_fp16.pt eval.json bench.json tests.log report.md"
for f in $OUTPUTS; do rm -f "$OUT/$f"; done
: > "$WORK/steps.tsv"
: > "$WORK/commands.txt"
plan() { echo "$1=$2" >> "$WORK/plan.txt"; }
say() { echo "[gpu_run $(( ($(now_ms) - T0) / 1000 ))s] $*"; }
left_s() { echo $(( (DEADLINE - $(now_ms)) / 1000 )); }   # whole seconds to the deadline
min() { if [ "$1" -lt "$2" ]; then echo "$1"; else echo "$2"; fi; }
max() { if [ "$1" -gt "$2" ]; then echo "$1"; else echo "$2"; fi; }
clamp() { min "$(max "$1" "$2")" "$3"; }

# run_step NAME LIMIT_S LOG CMD...: CMD under `timeout` (TERM at LIMIT_S, KILL 5 s later, its whole process
# group), output appended to LOG; its status and seconds go to steps.tsv, its command line to commands.txt.
run_step() {
    local name=$1 limit=$2 log=$3
    shift 3
    local quoted
    quoted=$(printf '%q ' "$@")
    printf '%s: %s\n' "$name" "${quoted% }" | sed "s#$WORK/#WORK/#g; s#$OUT/#OUT/#g" >> "$WORK/commands.txt"
    if [ "$limit" -lt 2 ]; then
        printf '%s\tskipped: no time left\t0\t%s\t-\n' "$name" "$limit" >> "$WORK/steps.tsv"
        say "$name: skipped (no time left)"
        return 1
    fi
    local start status rc secs
    start=$(now_ms)
    timeout -k 5 "$limit" "$@" < /dev/null >> "$log" 2>&1
    rc=$?
    secs=$(awk -v ms=$(( $(now_ms) - start )) 'BEGIN { printf "%.1f", ms / 1000 }')
    case $rc in
        0) status=ok ;;
        124|137) status="timed out (limit ${limit} s)" ;;
        *) status="failed (exit $rc)" ;;
    esac
    printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$name" "$status" "$secs" "$limit" "$rc" "$log" >> "$WORK/steps.tsv"
    say "$name: $status in $secs s"
    return $rc
}
report() {   # report.md (and eval.json) as they stand: a run cut short still leaves its report
    plan elapsed_s "$(( ($(now_ms) - T0) / 1000 ))"
    timeout -k 2 "$(clamp "$(( $(left_s) + 20 ))" 3 20)" "$PY" experiments/gpu_run_tools.py report --work "$WORK" \
        --out "$OUT/report.md" >> "$WORK/report.log" 2>&1 \
        || { printf '# GPU run report\n\nreport.md could not be written (see below); steps:\n\n```\n'; cat "$WORK/steps.tsv";
             printf '```\n\n```\n'; tail -c 3000 "$WORK/report.log"; printf '```\n'; } > "$OUT/report.md"
    sed -i '/^elapsed_s=/d' "$WORK/plan.txt"
}

say "work folder $WORK; budget $BUDGET_S s; outputs in $OUT"
echo "gpu_run: ${SETTINGS}bash experiments/gpu_run.sh OUT $MINUTES" >> "$WORK/commands.txt"
plan started "$(date -u +%Y-%m-%dT%H:%M:%SZ)"
plan minutes "$MINUTES"
plan budget_s "$BUDGET_S"
plan config "$CONFIG"
[ -n "${CONTINUE_FROM:-}" ] && plan continue_from "$CONTINUE_FROM"

# --- set-up: the wheels of the packages this machine lacks, the device, the machine -------------------------------
if [ -d "$WHEELS" ]; then
    missing=$(timeout 60 "$PY" experiments/gpu_run_tools.py missing-wheels "$WHEELS" 2>> "$WORK/install.log")
    if [ -n "$missing" ]; then
        SITE="$WORK/site"
        # shellcheck disable=SC2086
        run_step install "$(min 120 $(( BUDGET_S / 8 )))" "$WORK/install.log" "$PY" -m pip install -q --no-index \
            --no-deps --no-compile --no-cache-dir --disable-pip-version-check --upgrade --target "$SITE" $missing \
        || run_step "install (unzipped, pip failed)" 60 "$WORK/install.log" "$PY" -c "
import sys, zipfile
for wheel in sys.argv[2:]:
    zipfile.ZipFile(wheel).extractall(sys.argv[1])" "$SITE" $missing
        export PYTHONPATH="$SITE:$PYTHONPATH"
        plan install "$(for w in $missing; do basename "$w" | cut -d- -f1-2; done | paste -sd' ' -)"
    fi
fi
if [ "${DEVICE:-auto}" = auto ]; then
    DEVICE=$(timeout "$(clamp "$(left_s)" 5 90)" "$PY" -c "import torch; print('cuda' if torch.cuda.is_available() else 'cpu')" 2>/dev/null \
             || echo cpu)
fi
plan device "$DEVICE"
# the room type the config trains (its prior is sampled, evaluated and compared with the one shipped for that room)
ROOM=$(timeout 20 "$PY" -c "import sys; from pathlib import Path; from agents.config import read_yaml_settings
print(read_yaml_settings(Path(sys.argv[1])).get('room', 'bedroom'))" "$CONFIG" 2>> "$WORK/install.log" || echo bedroom)
plan room "$ROOM"
{
    echo "host: $(uname -n), $(nproc) CPU cores, $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 1048576}' /proc/meminfo) memory"
    if command -v nvidia-smi > /dev/null; then
        timeout 20 nvidia-smi --query-gpu=index,name,memory.total,driver_version --format=csv,noheader 2>&1 | sed 's/^/gpu: /'
        timeout 20 nvidia-smi 2>&1 | grep -m1 "CUDA Version" | sed 's/^/nvidia-smi: /'
    else
        echo "gpu: none (no nvidia-smi)"
    fi
    timeout 60 "$PY" -c "
import platform, sys, torch
print('python', platform.python_version(), sys.executable)
print('torch', torch.__version__, '| CUDA', torch.version.cuda, '| cuDNN', torch.backends.cudnn.version(),
      '| GPUs seen:', [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())])
import importlib.metadata as m
names = ('numpy', 'scipy', 'shapely', 'gymnasium', 'tensordict', 'torchrl', 'peft', 'tensorboard', 'pytest')
def v(n):
    try: return m.version(n)
    except Exception: return 'missing'
print('packages:', ', '.join(f'{n} {v(n)}' for n in names))" 2>&1 | tail -n 4
    echo "repository: $(git -C "$REPO" rev-parse --short HEAD 2>/dev/null || echo '(no git)')$(
        git -C "$REPO" status --porcelain 2>/dev/null | grep -q . && echo ' with local changes')"
} > "$WORK/machine.txt" 2>&1
say "device $DEVICE; $(grep -m1 '^gpu:' "$WORK/machine.txt")"

# --- 1. the CUDA tests --------------------------------------------------------------------------------------------
TESTS_TIMEOUT=${TESTS_TIMEOUT:-$(clamp $(( BUDGET_S * 15 / 100 )) 20 180)}
BENCH_TIMEOUT=${BENCH_TIMEOUT:-$(clamp $(( BUDGET_S * 15 / 100 )) 20 180)}
plan tests_timeout_s "$TESTS_TIMEOUT"
plan bench_timeout_s "$BENCH_TIMEOUT"
# shellcheck disable=SC2086
run_step tests "$(min "$TESTS_TIMEOUT" $(( $(left_s) - SAFETY_S )))" "$WORK/tests.log" \
    "$PY" -m pytest -o addopts= -v -rA -p no:cacheprovider $TESTS
cp "$WORK/tests.log" "$OUT/tests.log" 2>/dev/null || echo "(the tests did not run)" > "$OUT/tests.log"
report

# --- 2. the pretraining benchmark ---------------------------------------------------------------------------------
if [ -z "${BENCH_ARGS:-}" ]; then
    if [ "$DEVICE" = cpu ]; then BENCH_ARGS="--presets tiny --batches 64 --rooms 200 --repeats 1"
    else BENCH_ARGS="--presets small --batches 4096,16384 --repeats 3"; fi
fi
# shellcheck disable=SC2086
run_step benchmark "$(min "$BENCH_TIMEOUT" $(( $(left_s) - SAFETY_S )))" "$WORK/bench.log" \
    "$PY" benchmarks/bench_pretrain.py --device "$DEVICE" --json "$WORK/bench_raw.json" $BENCH_ARGS
timeout 20 "$PY" experiments/gpu_run_tools.py bench-json --work "$WORK" --out "$OUT/bench.json" >> "$WORK/report.log" 2>&1
report

# --- the plan of what is left: training until the evaluation's reserve ---------------------------------------------
# The evaluation (the trained prior's sampling, `iarcs evaluate`, the extra figures, the bed ablation; each a new
# Python process) measured: on 2 CPU cores, 500 floors take about 51 s to sample with the small prior, 16 s to
# evaluate (4 s without the FID/KID/SCA features) and 26 s for the bed ablation; on a GPU the sampling and the bed
# ablation take seconds and the metrics run on the machine's CPU cores. Reserve: fixed + per floor.
if [ "$DEVICE" = cpu ]; then FIXED_S=30; PER_FLOOR_MS=250; else FIXED_S=50; PER_FLOOR_MS=80; fi
LEFT=$(( $(left_s) - SAFETY_S ))
FLOORS=$EVAL_FLOORS
RESERVE=${EVAL_RESERVE:-$(( FIXED_S + FLOORS * PER_FLOOR_MS / 1000 ))}
CAP=$(( LEFT * 35 / 100 ))
if [ -z "${EVAL_RESERVE:-}" ] && [ "$RESERVE" -gt "$CAP" ]; then   # a short budget: evaluate fewer floors
    FLOORS=$(clamp $(( (CAP - FIXED_S) * 1000 / PER_FLOOR_MS )) 20 "$EVAL_FLOORS")
    RESERVE=$(( FIXED_S + FLOORS * PER_FLOOR_MS / 1000 ))
    [ "$FLOORS" -lt "$EVAL_FLOORS" ] && plan eval_note "$FLOORS of the $EVAL_FLOORS floors asked: the budget left $LEFT s after the tests and the benchmark, and the evaluation keeps at most 35% of it ($CAP s; it needs about $FIXED_S s + $PER_FLOOR_MS ms per floor on $DEVICE)"
fi
WINDOW=$(( LEFT - RESERVE ))
TRAIN_MARGIN=$(( 10 + WINDOW * 3 / 100 ))   # start-up (imports, CUDA) before the clock of --time-budget starts
TRAIN_BUDGET=$(( WINDOW - TRAIN_MARGIN ))
plan eval_floors_asked "$EVAL_FLOORS"
plan eval_floors "$FLOORS"
plan eval_reserve_s "$RESERVE"
plan train_window_s "$WINDOW"
plan train_budget_s "$TRAIN_BUDGET"
TRAIN_END=$(( $(now_ms) + WINDOW * 1000 ))
until_s() { echo $(( ($1 - $(now_ms)) / 1000 )); }
mkdir -p "$WORK/eval/shipped" "$WORK/eval/trained"

# eval_prior NAME PRIOR END_MS: sample the prior on the floors, `iarcs evaluate`, the extra figures, the bed ablation;
# each under a limit that ends by END_MS and keeps a little for the steps after it.
eval_prior() {
    local name=$1 prior=$2 end=$3 dir="$WORK/eval/$1"
    plan "${name}_prior" "$prior"
    run_step "$name: sample" "$(( $(until_s "$end") - 12 ))" "$dir/log" "$PY" -m experiments.cli sample --room "$ROOM" \
        --checkpoint "$prior" --floors "$WORK/floors.json" --num-scenes "$FLOORS" --seed 0 --device "$DEVICE" \
        --out "$dir/samples.json" || return 1
    run_step "$name: evaluate" "$(( $(until_s "$end") - 6 ))" "$dir/log" "$PY" -m experiments.cli evaluate \
        --scenes "$dir/samples.json" --reference "$WORK/floors.json" --out "$dir/iarcs.json" --name "$name prior"
    run_step "$name: figures" "$(( $(until_s "$end") - 3 ))" "$dir/log" "$PY" experiments/gpu_run_tools.py figures \
        --samples "$dir/samples.json" --reference "$WORK/floors.json" --out "$dir/figures.json"
    [ "$ROOM" = bedroom ] || return 0
    run_step "$name: bed ablation" "$(until_s "$end")" "$dir/log" "$PY" experiments/gpu_run_tools.py bed-ablation \
        --prior "$prior" --reference "$WORK/floors.json" --device "$DEVICE" --out "$dir/bed_ablation.json"
}
floors() {
    run_step floors "$1" "$WORK/floors.log" "$PY" -m experiments.cli data generate --room "$ROOM" \
        --num-scenes "$FLOORS" --seed 777 --out "$WORK/floors.json"
}

# --- 3. training; meanwhile the held-out floors and the shipped prior's evaluation ------------------------------------
# (a few CPU threads for it: the training's loop needs a free core to launch its GPU work)
( export OMP_NUM_THREADS=$(clamp $(( $(nproc) / 4 )) 1 4)
  floors "$(min 120 $(( WINDOW / 2 )))" && eval_prior shipped "agents/checkpoints/${ROOM}_small.pt" "$TRAIN_END" ) \
    > "$WORK/baseline.log" 2>&1 &
BASELINE=$!
if [ "$TRAIN_BUDGET" -ge 10 ]; then
    TRAIN_ARGS=(--config "$CONFIG" --out "$WORK/run" --time-budget "$(awk -v s="$TRAIN_BUDGET" 'BEGIN { printf "%.3f", s / 60 }')"
                --device "$DEVICE")
    [ -n "${CONTINUE_FROM:-}" ] && TRAIN_ARGS+=(--continue-from "$CONTINUE_FROM")
    run_step train "$(until_s "$TRAIN_END")" "$WORK/train.log" "$PY" -m experiments.cli pretrain "${TRAIN_ARGS[@]}"
else
    printf 'train\tskipped: %s s left for it\t0\t%s\t-\n' "$WINDOW" "$WINDOW" >> "$WORK/steps.tsv"
fi
# a run stopped by its hard limit still has its last checkpoint: export that
if [ -f "$WORK/run/train_state.pt" ]; then
    run_step export "$(min 60 $(( $(left_s) - SAFETY_S - 10 )))" "$WORK/export.log" "$PY" experiments/gpu_run_tools.py \
        export --state "$WORK/run/train_state.pt" --dest "$WORK/prior_fp16.pt" --json "$WORK/export.json" \
        && cp "$WORK/prior_fp16.pt" "$OUT/prior_fp16.pt"
fi
# the shipped prior's evaluation ends by TRAIN_END (+5 s for a kill); wait for it, never past the deadline
while kill -0 "$BASELINE" 2> /dev/null && [ "$(left_s)" -gt "$SAFETY_S" ]; do sleep 1; done
kill -0 "$BASELINE" 2> /dev/null && { pkill -TERM -P "$BASELINE"; kill -TERM "$BASELINE"; } 2> /dev/null
report

# --- 4. the trained prior's evaluation ---------------------------------------------------------------------------
EVAL_END=$(( DEADLINE - SAFETY_S * 1000 ))
[ -s "$WORK/floors.json" ] || floors "$(( $(until_s "$EVAL_END") / 3 ))"
if [ -f "$WORK/prior_fp16.pt" ] && [ -s "$WORK/floors.json" ]; then
    eval_prior trained "$WORK/prior_fp16.pt" "$EVAL_END"
fi
timeout -k 2 "$(clamp $(( $(left_s) - 4 )) 3 30)" "$PY" experiments/gpu_run_tools.py eval-json --work "$WORK" \
    --out "$OUT/eval.json" >> "$WORK/report.log" 2>&1
report
say "done in $(( ($(now_ms) - T0) / 1000 )) s (budget $BUDGET_S s): $(cd "$OUT" && ls $OUTPUTS 2>/dev/null | tr '\n' ' ')"
