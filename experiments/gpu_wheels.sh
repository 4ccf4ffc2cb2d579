#!/usr/bin/env bash
# Builds .whl/ in the repository root: the wheels that experiments/gpu_run.sh installs on a bare CUDA machine
# (Python 3.12, x86_64, torch and numpy/scipy/pillow/pyyaml/tqdm/tensorboard/peft/safetensors/pytest there, no
# package index) for the packages that machine lacks and the code the run executes imports (docs/gpu.md):
#
#   shapely      iarcs_env (floor plans, metrics): every command
#   gymnasium    iarcs_env/__init__.py registers the environments: every command
#   tensordict   agents/ddpo.py: the CUDA test of DDPO (tests/test_device.py)
#   torchrl      agents/ddpo.py (the PPO loss) and agents/policy.py: the same test
#   and their dependencies that the machine may lack (the run installs only the missing ones).
#
# litellm is not needed (rewards/llm.py imports it only to call a model). Versions: pyproject.toml's pins, and the
# dependencies' as installed in .venv (the versions the tests pass with). Needs network access to the package
# registry, here only.
#
#   bash experiments/gpu_wheels.sh          # then carry .whl to the device (see docs/gpu.md)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}   # the environment whose versions are pinned
DEST=.whl
# distribution names: the pinned four, then their dependencies (Requires-Dist of each wheel, extras left out)
PACKAGES="shapely gymnasium tensordict torchrl cloudpickle farama-notifications typing-extensions pyvers orjson
importlib-metadata zipp packaging hoptorch"

mkdir -p .git/info
grep -qxF '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
rm -rf "$DEST"
mkdir -p "$DEST"
specs=()
for name in $PACKAGES; do
    version=$("$PY" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$name") || {
        echo "gpu_wheels: $name is not installed in $PY's environment (run make install first)" >&2; exit 1; }
    specs+=("$name==$version")
done
echo "gpu_wheels: downloading ${specs[*]}"
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d "$DEST" "${specs[@]}" 2>&1 \
    | grep -v "is ignored: it is neither a file nor a directory" || true
count=$(ls "$DEST"/*.whl 2>/dev/null | wc -l)
if [ "$count" -ne "$(echo $PACKAGES | wc -w)" ]; then
    echo "gpu_wheels: expected $(echo $PACKAGES | wc -w) wheels, got $count" >&2
    exit 1
fi
# every dependency a wheel declares (no extras) is either in .whl or on the GPU machine already
for w in "$DEST"/*.whl; do
    deps=$(unzip -p "$w" '*.dist-info/METADATA' | grep '^Requires-Dist' | grep -v 'extra ==' \
           | sed -E 's/^Requires-Dist: *([A-Za-z0-9_.-]+).*/\1/' | tr '\n' ' ' || true)
    echo "  $(basename "$w") ($(du -k "$w" | cut -f1) KiB)${deps:+: needs $deps}"
done
echo "gpu_wheels: $count wheels, $(du -sh "$DEST" | cut -f1) in $DEST (carry it: docs/gpu.md)"
