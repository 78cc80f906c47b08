# torchmm: `make run` (set up + default study) and `make test` (set up + test suite).
SHELL  := /bin/bash
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
ARGS   ?=
# test processes (pytest-xdist): the CPUs, at most 4 (each process imports torch; files stay whole)
JOBS   ?= $(shell n=$$(nproc 2>/dev/null || echo 1); [ $$n -gt 4 ] && n=4; echo $$n)

.PHONY: install run test test-slow test-all bench gpu-wheels clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@echo "torchmm install [1/3]: pip"
	$(BIN)/python -m pip install --quiet --upgrade pip
	@echo "torchmm install [2/3]: torch 2.13.0 (CPU build first: an unpinned torch would pull a multi-GB CUDA build)"
	$(BIN)/python -m pip install --quiet torch==2.13.0
	@echo "torchmm install [3/3]: torchmm and its dependencies (about a minute on a fresh machine)"
	set -o pipefail; $(BIN)/python -m pip install -e ".[dev]" 2>&1 | { grep --line-buffered -E "^(Collecting|Successfully installed|ERROR)" || true; }
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/torchmm-run $(ARGS)

# one torch/OpenMP thread per process: the suite's tensors are small (see tests/conftest.py)
test: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -m "not slow" -n $(JOBS) --dist loadfile $(ARGS)

test-slow: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -m slow $(ARGS)

test-all: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest $(ARGS)

bench: $(STAMP)
	$(BIN)/python benchmarks/imm_vs_filterpy.py $(ARGS)

# for a lent GPU machine (benchmarks/gpu_session.sh): the pure-Python packages its image lacks, as wheels
gpu-wheels: $(STAMP)
	rm -rf .whl && mkdir -p .whl
	$(BIN)/python -m pip wheel --quiet --no-deps -w .whl hydra-core==1.3.8 omegaconf==2.3.1 antlr4-python3-runtime==4.9.3 \
		hydra-joblib-launcher==1.2.0

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache .hypothesis
