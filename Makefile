# Two commands a user needs: `make demo` and `make test` (see README.md).
SHELL := /bin/bash
.DEFAULT_GOAL := help
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.synced
PYTEST_DEFAULT := -m "not slow and not bench and not gpu"

export DGS_NO_PROGRESS ?=

.PHONY: help env test test-all bench demo demo-eval lint clean

help:
	@echo "make demo      run the main job on a built-in scene"
	@echo "make demo-eval score it against a baseline on held-out views (long)"
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

# The main job on the built-in `llff_like` scene (forward-facing, 12 views, Gaussian noise
# sigma 25/255), at a reduced size for 2 CPU cores: render the scene, then run the two-round
# Denoise-GS pipeline on its noisy photos (poses, splat scene, renders, report.md).
# `make demo-eval` then scores it against InstantSplat-style reconstruction of the noisy
# photos on held-out views (it re-runs both methods on the training split: much longer).
DEMO_OUT ?= runs/demo
DEMO_SIZE ?= 192x144
demo: $(STAMP)
	$(VENV)/bin/data-synth render llff_like --out $(DEMO_OUT)/data --size $(DEMO_SIZE) --views 12
	$(VENV)/bin/denoise-gs run $(DEMO_OUT)/data/images --out $(DEMO_OUT)/run --preset fast --views 8
	@echo
	@echo "pipeline report: $(DEMO_OUT)/run/report.md"

demo-eval: $(STAMP)
	test -d $(DEMO_OUT)/data || $(VENV)/bin/data-synth render llff_like --out $(DEMO_OUT)/data --size $(DEMO_SIZE) --views 12
	$(VENV)/bin/denoise-gs eval $(DEMO_OUT)/data --out $(DEMO_OUT)/eval --preset fast --seeds 1 \
		--methods instantsplat denoise_gs
	@echo
	@echo "evaluation report: $(DEMO_OUT)/eval/results.md"

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) .tools .pytest_cache
