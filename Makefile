# The two commands of the README: `make demo` and `make test`. Both set up .venv when needed.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.softac-installed
TEST_STAMP := $(VENV)/.softac-test-installed
DEMO   := runs/demo/$(shell date +%Y%m%d-%H%M%S)

.PHONY: demo test test-deps test-venv min-deps docs-deps test-fast test-isa test-min test-min-full bench docs docs-site venv clean-venv render-deps system-deps

venv: $(STAMP)

# the base install only (JAX from PyPI; no PyTorch, no Ray): what `make demo` needs
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e .
	@touch $@

# the test extra adds pytest, hypothesis, the [ray] extra (the sweep tests run a local Ray), [export] (onnx) and
# [robotics] (Gymnasium-Robotics, with the MuJoCo releases its Fetch envs work with). One pip resolve and one
# build of softac for the lot on a fresh clone (the base install first, then the extra, resolved and built twice:
# issue 64); it includes the base install, so `make demo` after it installs nothing more.
$(TEST_STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	@touch $(STAMP) $@

# the test venv and the Debian packages, without running anything
test-deps: $(TEST_STAMP) system-deps

# each install on its own: .ci/run runs them at once (the .venv, then its docs extra; .venv-min; the Debian
# packages), since they wait on the package registry and dpkg more than on the CPU (issue 64)
test-venv: $(TEST_STAMP)

# Debian packages, installed when missing and we may (root, or passwordless sudo):
# libosmesa6 lets MuJoCo render headless where EGL does not work; chromium runs the report test.
APT := $(shell if [ "$$(id -u)" = 0 ]; then echo apt-get; elif sudo -n true 2>/dev/null; then echo "sudo apt-get"; fi)
define apt_install
	@missing="$(strip $(1))"; \
	if [ -n "$$missing" ]; then \
	  if [ -n "$(APT)" ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing Debian packages: $$missing"; \
	    $(APT) update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive $(APT) install -y -qq --no-install-recommends $$missing >/dev/null; \
	  else echo "note: cannot install $$missing (not root, no apt-get); tests that need them skip"; fi; \
	fi
endef
NEED_OSMESA   = $(shell ldconfig -p 2>/dev/null | grep -q libOSMesa || echo libosmesa6)
NEED_CHROMIUM = $(shell command -v chromium >/dev/null 2>&1 || echo chromium)

render-deps:
	$(call apt_install,$(NEED_OSMESA))

system-deps:
	$(call apt_install,$(NEED_OSMESA) $(NEED_CHROMIUM))

demo: $(STAMP) render-deps
	$(BIN)/softac train --target-return 1000 --out $(DEMO)
	$(BIN)/softac eval $(DEMO) --episodes 10
	$(BIN)/softac baselines --env InvertedPendulum-v5 --out $(DEMO)
	$(BIN)/softac plot $(DEMO)
	-$(BIN)/softac video $(DEMO)
	$(BIN)/softac report $(DEMO)
	@echo ""
	@echo "demo run:  $(DEMO)"
	@echo "  plots:   $(DEMO)/plots/learning_curve.png, $(DEMO)/plots/metrics.png"
	@echo "  video:   $$(ls $(DEMO)/videos/*.mp4 2>/dev/null || echo 'none (rendering unavailable)')"
	@echo "  report:  $(DEMO)/report.html"

# the suite on two pytest-xdist workers (the Ray sweeps on one of them, in turn, from the start; the fast tests
# before the slow ones: tests/conftest.py); PYTEST_WORKERS=0 runs it in this one process; the 30 slowest tests
# are listed at the end (CI's 20-minute aim). In CI (CI=true) the first failure ends the run, so that a broken
# fast test fails CI in minutes, before the slow tests and steps (issue 64).
PYTEST_WORKERS ?= 2
XDIST := -n $(PYTEST_WORKERS) --dist loadgroup
STOP_EARLY := $(if $(filter true 1,$(CI)),--maxfail=1)

# XLA's fast-compile flags in make test (issue 64): LLVM at level 0 and XLA's earlier fused-loop emitters, those of
# them this jaxlib knows (tests/fast_compile.py prints them, and says what each saves and what it changes). The
# code users run, at XLA's defaults, is tested by the `users_xla` tests, the learning test, test-isa and test-min.
# A flag of XLA_FLAGS's own comes after these and wins.
FAST_COMPILE = XLA_FLAGS="$$($(BIN)/python tests/fast_compile.py) $$XLA_FLAGS"

test: $(TEST_STAMP) system-deps
	$(FAST_COMPILE) $(BIN)/python -m pytest -q $(XDIST) $(STOP_EARLY) --durations=30

# without the learning test, the kill/signal campaigns, the Ray sweeps and the bench runs (CI runs them all)
test-fast: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -m "not slow and not faults and not ray and not bench"

# the numerics-sensitive tests (export parity, the losses against hand computations, CrossQ, the bf16 choice) as
# on a CPU without AVX-512: XLA limited to AVX2 sums in other orders than on this machine's own instruction set.
# The `exact` tests (a resumed run against a straight one, both on this machine) compare a CPU with itself: they
# run in make test and test-min, not here.
# They run at XLA's default optimisation level, as users' programs compile (make test compiles at level 0).
# On a CPU whose newest instruction set is ISA or older (an AVX2-only AMD EPYC), the limit changes nothing: XLA
# compiled the same object files with it as without (issue 64), so test-isa runs them without it, and says so.
ISA ?= AVX2
NUMERICS_TESTS = $(BIN)/python -m pytest -q $(XDIST) $(STOP_EARLY) -m "numerics and not ray"
ISA_TESTS = XLA_FLAGS="$$XLA_FLAGS --xla_cpu_max_isa=$(ISA)" $(NUMERICS_TESTS)
test-isa: $(TEST_STAMP)
	@if $(BIN)/python -c "import sys; from softac.base.cpus import xla_limit_changes_code; sys.exit(not xla_limit_changes_code('$(ISA)'))"; then \
	  echo '$(ISA_TESTS)'; $(ISA_TESTS); \
	else \
	  echo "test-isa: this CPU has no instruction set newer than $(ISA) ($$($(BIN)/python -c 'from softac.base.cpus import machine_description; print(machine_description())')): XLA compiles the same code with the limit as without, so the numerics tests run here without it, at XLA's default optimisation level"; \
	  echo '$(NUMERICS_TESTS)'; $(NUMERICS_TESTS); \
	fi

# the lowest supported versions of JAX, Gymnasium, MuJoCo, optax, NumPy and SciPy (.ci/min-versions.txt, the
# floors in pyproject.toml), in their own .venv-min, with the [export] extra. test-min (in CI) runs the numerics
# and exact tests there (the losses, exact resume through the envs' saved state, exports); test-min-full runs
# all but the Ray, fault, learning and bench tests (the W&B and MLflow tests skip there): run it when a floor changes
MIN_VENV  := .venv-min
MIN_STAMP := $(MIN_VENV)/.softac-min-installed
$(MIN_STAMP): pyproject.toml .ci/min-versions.txt
	@test -x $(MIN_VENV)/bin/python || $(PYTHON) -m venv $(MIN_VENV)
	$(MIN_VENV)/bin/python -m pip install -q --upgrade pip
	$(MIN_VENV)/bin/python -m pip install -q -c .ci/min-versions.txt -e ".[export]" "pytest>=7" "hypothesis>=6.80" \
	  "pytest-randomly>=3.15" "pytest-xdist>=3.5"
	@touch $@

min-deps: $(MIN_STAMP)

test-min: $(MIN_STAMP)
	$(MIN_VENV)/bin/python -m pytest -q -p no:cacheprovider $(XDIST) $(STOP_EARLY) -m "(numerics or exact) and not ray and not robotics"

test-min-full: $(MIN_STAMP)
	$(MIN_VENV)/bin/python -m pytest -q -p no:cacheprovider $(XDIST) -m "not slow and not faults and not ray and not bench and not robotics"

# softac vs Stable-Baselines3 vs SBX on this machine; torch 2.13.0 (CPU build) goes in first so that
# no CUDA packages are pulled. BENCH_ARGS adds options, e.g. BENCH_ARGS="--repeats 5".
BENCH_STAMP := $(VENV)/.softac-bench-installed
$(BENCH_STAMP): $(TEST_STAMP)
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[test,bench]"  # test includes [ray]: `softac sweep --framework sb3`
	@touch $@

bench: $(BENCH_STAMP)
	$(BIN)/softac bench --solve $(BENCH_ARGS)

# the configuration reference's table (docs/reference/config.md) comes from SACConfig
docs: $(STAMP)
	$(BIN)/python scripts/write_config_table.py

# the documentation site (mkdocs.yml, docs/): built into site/ with --strict, so a broken link, anchor or API
# reference fails the build (CI runs it)
DOCS_STAMP := $(VENV)/.softac-docs-installed
$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e ".[docs]"
	@touch $@

docs-deps: $(DOCS_STAMP)

docs-site: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

clean-venv:
	rm -rf $(VENV)
