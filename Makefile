# metampc: set-up, build, test and run. See README.md.
SHELL := /bin/bash
.DEFAULT_GOAL := help
ENV := source scripts/env.sh
PYTEST_ARGS ?=
# pytest-xdist workers of `make test` (0: one process, no workers)
TEST_JOBS ?= 2
# Threads of BLAS and OpenMP (torch) in each test process: the workers already fill the cores,
# and OpenBLAS threads that spin for a busy core made one test 4x slower (3 min, not 57 s).
TEST_THREADS ?= 1
RUN_ARGS ?=

.PHONY: help setup build test lint run clean

help:
	@echo "make run    set up, build and run the default experiment"
	@echo "make test   set up, build and run every test"
	@echo "make setup  create/update .venv (idempotent)"
	@echo "make build  colcon build of src/ into build/ and install/ (incremental)"
	@echo "make lint   flake8 over src/, scripts/, test/ and examples/"
	@echo "make clean  remove build/, install/ and log/ (keeps .venv)"

setup:
	@bash scripts/setup.sh

build: setup
	@$(ENV) && set -o pipefail && flock .build.lock colcon --log-base log build \
	  --base-paths src --symlink-install --event-handlers console_direct- \
	  --cmake-args -DBUILD_TESTING=OFF -Wno-dev 2>&1 \
	  | { grep -vE '^(Starting|Finished) |local_setup' || true; }

lint: setup
	@$(ENV) && flake8 src scripts test examples

test: build
	@$(ENV) && OPENBLAS_NUM_THREADS=$(TEST_THREADS) OMP_NUM_THREADS=$(TEST_THREADS) \
	  python -m pytest -n $(TEST_JOBS) --dist loadgroup $(PYTEST_ARGS)

run: build
	@$(ENV) && python scripts/run_experiment.py $(RUN_ARGS)

clean:
	rm -rf build install log
