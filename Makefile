# The two commands of the README: `make demo` and `make test`. Both set up .venv when needed.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.softac-installed
DEMO   := runs/demo/$(shell date +%Y%m%d-%H%M%S)

.PHONY: demo test test-fast bench docs venv clean-venv

venv: $(STAMP)

# base install only (JAX from PyPI, no PyTorch); the test extra adds pytest
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	@touch $@

demo: $(STAMP)
	$(BIN)/softac train --target-return 1000 --out $(DEMO)
	$(BIN)/softac eval $(DEMO) --episodes 10
	@echo "demo run: $(DEMO) (progress.csv, eval.csv, checkpoints/, tb/)"

test: $(STAMP)
	$(BIN)/python -m pytest -q

# unit tests only: skips the learning tests
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

# softac vs Stable-Baselines3 vs SBX on this machine; torch 2.13.0 (CPU build) goes in first so that
# no CUDA packages are pulled. BENCH_ARGS adds options, e.g. BENCH_ARGS="--repeats 5".
BENCH_STAMP := $(VENV)/.softac-bench-installed
$(BENCH_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[test,bench]"
	@touch $@

bench: $(BENCH_STAMP)
	$(BIN)/softac bench --solve $(BENCH_ARGS)

# the README's config table comes from SACConfig
docs: $(STAMP)
	$(BIN)/python scripts/write_config_table.py

clean-venv:
	rm -rf $(VENV)
