# `make demo` and `make test` each create or reuse .venv and install what they need.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)
DEMO_OUT ?= out/demo
# The 3D viewer's script: three.js and viewer/src bundled from the pinned npm packages of viewer/.
VIEWER := iarcs_env/data/viewer.js

.PHONY: install demo test bench clean viewer

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[dev]"
	rm -f $(VENV)/.installed-*; touch $(STAMP)

$(VIEWER): viewer/package.json viewer/package-lock.json viewer/src/viewer.js
	@if ! command -v npm >/dev/null; then \
		echo "npm not found: the 3D viewer is not built (install node and npm, then run make viewer)"; \
	elif (cd viewer && npm ci --no-audit --no-fund --loglevel=error); then \
		cd viewer && npm run --silent build; \
	else echo "npm could not install the viewer's packages (is the npm registry reachable?): the 3D viewer is not built"; fi

viewer: $(VIEWER)

install: $(STAMP) $(VIEWER)

demo: $(STAMP) $(VIEWER)
	$(VENV)/bin/iarcs demo --out $(DEMO_OUT)

test: $(STAMP) $(VIEWER)
	$(PY) -m pytest -rf tests

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) out viewer/node_modules $(VIEWER)
