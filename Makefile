# The two commands of the README: `make demo` and `make test`. Both set up .venv first.
# `make test` leaves out the tests marked slow; `make test-all` runs every test, and
# `make test-faults` the whole fault-injection suite (kill and resume at every stage).
VENV ?= .venv
PYTHON ?= python3
TORCH_SPEC ?= torch==2.13.0
PY := $(VENV)/bin/python

.PHONY: setup demo test test-all test-faults lint docs bench cpu-cores mutation gpu-check gpu-check-quick

setup: $(VENV)/.installed

# uv installs in ~20 s what pip took ~90 s for (most of it unpacking torch). uv reads no pip
# configuration, so pip's own find-links (a folder of local wheels, where the machine has one)
# are handed to it. Neither installer's bytecode is asked for: compiling every installed file
# (uv's --compile-bytecode) cost ~23 s of setup, and a run imports about a fifth of them. The
# targets that run Python ($(RUN)) let it write the bytecode of what it imports, once, even
# where PYTHONDONTWRITEBYTECODE is set (as on the development machines): without any, every
# Python process a test starts compiled torch's sources again (the command line's start: 7 s
# -> 17 s). INSTALLER='pip' installs with pip as before.
# PIP_LINKS is expanded only when an install runs (`=`, not `:=`): other targets never ask pip.
INSTALLER ?= uv
PIP_LINKS = $(shell $(PYTHON) -m pip config get global.find-links 2>/dev/null)
ifeq ($(INSTALLER),uv)
INSTALL = $(PY) -m uv pip install --quiet --python $(PY) $(addprefix --find-links ,$(PIP_LINKS))
else
INSTALL = $(PY) -m pip install --quiet
endif
RUN := env -u PYTHONDONTWRITEBYTECODE

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(if $(filter uv,$(INSTALLER)),$(PY) -m pip install --quiet uv)
	$(INSTALL) "$(TORCH_SPEC)"
	$(INSTALL) -e ".[test]"
	touch $@

demo: setup
	$(RUN) $(PY) -m torchrl_recon.cli explore recipes/industrial_benchmark/explore_smoke.yaml

# Tests run in parallel workers (pytest-xdist), one per core; PYTEST_WORKERS=0 runs them in-process.
PYTEST_WORKERS ?= auto

test: setup
	$(PY) -m ruff check .
	$(RUN) $(PY) -m pytest -q -m "not slow" -n $(PYTEST_WORKERS) --dist worksteal

test-all: setup
	$(PY) -m ruff check .
	$(RUN) $(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist worksteal

test-faults: setup
	$(RUN) $(PY) -m pytest -q -rP tests/experiments/test_fault_injection.py

lint: setup
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

# The Sphinx site: the guides and the API reference (docs/conf.py); warnings are errors. Open
# docs/_build/html/index.html. No network is used (`make setup` installs the `docs` extra).
DOCS_OUT ?= docs/_build

docs: setup
	$(PY) -m sphinx -W --keep-going -n -b html -d $(DOCS_OUT)/doctrees docs $(DOCS_OUT)/html
	@echo "open $(DOCS_OUT)/html/index.html"

bench: setup
	$(PY) benchmarks/env_throughput.py
	$(PY) benchmarks/uncertainty_overhead.py
	$(PY) benchmarks/window_scoring.py
	$(PY) benchmarks/planner_speed.py
	$(PY) benchmarks/gradient_planning.py
	$(PY) benchmarks/training_speed.py
	$(PY) benchmarks/gemm_floor.py
	$(PY) benchmarks/cpu_blocks.py

# PlanningModel(threads=N) on a machine with more cores (docs/benchmarks.md#row-blocks-on-two-cpu-cores):
# the pass and a CEM call at N = 2, 4, 8 and 16 threads, each against one eager call and against
# N processes (the machine's ceiling). A few minutes; the first compile of each N takes ~30 s.
cpu-cores: setup
	for n in 2 4 8 16; do $(PY) benchmarks/cpu_blocks.py --block-threads $$n --repeats 10 || exit 1; done

# One command for a GPU machine (docs/benchmarks.md#gpu-check): the CUDA tests, every benchmark
# with --device cuda and a smoke run of each experiment kind on device=cuda, within 8 minutes;
# the report is $(GPU_CHECK_OUT)/gpu_check.md. Without a GPU it runs the test steps and skips the rest.
GPU_CHECK_OUT ?= outputs/gpu_check

gpu-check: setup
	$(PY) benchmarks/gpu_check.py --out $(GPU_CHECK_OUT)

# The planners' and fits' CUDA tests and benchmarks only (K = 1,000 and 10,000), to iterate on a GPU.
gpu-check-quick: setup
	$(PY) benchmarks/gpu_check.py --out $(GPU_CHECK_OUT) --quick

# Mutation testing (docs/testing.md); not part of `make test`. It runs in a copy of the work
# tree under MUTATION_DIR. MUTANTS: mutmut mutant-name globs (default: the sample in
# tests/mutation/sample.txt; MUTANTS='*' for every mutant of the files in tests/mutation/setup.cfg).
MUTATION_DIR ?= /tmp/torchrl_recon-mutation
MUTATION_JOBS ?= 2
MUTANTS ?= $(shell cat tests/mutation/sample.txt)

mutation: setup
	$(PY) -m pip install --quiet "mutmut>=3.8,<4"
	rm -rf $(MUTATION_DIR) && mkdir -p $(MUTATION_DIR)
	git ls-files --cached --others --exclude-standard | while read -r f; do [ -e "$$f" ] && echo "$$f"; done \
		| tar -cf - -T - | tar -xf - -C $(MUTATION_DIR)
	cp tests/mutation/setup.cfg $(MUTATION_DIR)/setup.cfg
	set -f; cd $(MUTATION_DIR) && env -u PYTHONPATH OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
		nice -n 19 $(abspath $(PY)) -m mutmut run --max-children $(MUTATION_JOBS) $(MUTANTS)
	set -f; $(PY) tests/mutation/score.py $(MUTATION_DIR)/mutants $(MUTANTS)
