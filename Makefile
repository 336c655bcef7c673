# Two commands a user needs: `make demo` and `make test` (see README.md).
SHELL := /bin/bash
.DEFAULT_GOAL := help
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.synced
PYTEST_DEFAULT := -m "not slow and not bench and not gpu"

export DGS_NO_PROGRESS ?=

.PHONY: help env test test-all bench demo lint clean

help:
	@echo "make demo      run the main job on a built-in scene"
	@echo "make test      set up the environment (first time) and run the default tests"
	@echo "make test-all  all tests, slow ones included"
	@echo "make bench     benchmarks -> docs/benchmarks.md"
	@echo "make lint      ruff"

# The environment is rebuilt only when the lockfile or pyproject changes.
$(STAMP): uv.lock pyproject.toml tools/setup_env.sh
	bash tools/setup_env.sh
	@touch $(STAMP)

env: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest $(PYTEST_DEFAULT)

test-all: $(STAMP)
	$(PY) -m pytest

bench: $(STAMP)
	$(PY) benchmarks/run_all.py $(ONLY)

demo: $(STAMP)
	$(PY) -m eval.demo

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) .tools .pytest_cache
