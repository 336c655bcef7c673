# Two commands a user needs: `make demo` and `make test` (see README.md).
SHELL := /bin/bash
.DEFAULT_GOAL := help
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.synced
PYTEST_DEFAULT := -m "not slow and not bench and not gpu"
# The tests run in TEST_WORKERS processes (pytest-xdist; one per core, at most 4, each with one OpenMP and
# BLAS thread, tests/conftest.py); TEST_WORKERS=0 runs them in this process. On 2 cores the default suite
# takes about 0.6x the time of one process (docs/bench/test_suite.md).
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); if [ "$$n" -gt 4 ]; then n=4; fi; if [ "$$n" -lt 2 ]; then n=0; fi; echo $$n)

export DGS_NO_PROGRESS ?=

.PHONY: help env test test-all bench demo demo-eval lint clean

help:
	@echo "make demo      run the pipeline on a built-in scene, then score it on held-out views"
	@echo "make demo-eval the demo plus more baselines (3DGS with true poses, NLM, round 1; long)"
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
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile $(PYTEST_DEFAULT)

test-all: $(STAMP)
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile

# The benchmarks also need the `bench` dependency group (PyWavelets, bm3d: classical baselines).
bench: $(STAMP)
	bash tools/setup_env.sh --group bench
	$(PY) benchmarks/run_all.py $(ONLY)

# The main job on the built-in `llff_like` scene (forward-facing, Gaussian noise sigma 25/255),
# reduced for 2 CPU cores: 256x192 images, 10 views (8 training + 2 held out), the `fast` preset
# (one round; its splat takes back half of the noisy photos' finest band, `SplatSettings.noisy_detail`;
# K = 6 views would apply to a second round, `--rounds 2`). `denoise-gs eval` runs the product on the
# 8 noisy training photos (poses, splat scene, renders, report.md in runs/llff_like/seed0/product) and
# the InstantSplat-style baseline (b), then scores both on the held-out views (PSNR/SSIM/LPIPS against
# the clean images, pose errors). The two runs are independent, so with DEMO_WORKERS=2 (the default
# where the machine has 2 cores or more) they run side by side as two one-core Ray tasks: the same
# scores to the last digit, about 0.8x the wall time of one after the other on 2 cores
# (docs/bench/pipeline_demo.md); DEMO_WORKERS=1 runs them in turn without Ray.
# `make demo-eval` adds the other baselines (3DGS with true poses, NLM + InstantSplat, round 1 only).
# 256x192 rather than 160x120: at 160x120 the views often do not determine the focal length and the
# alignment of the denoised photos was several degrees off (docs/benchmarks.md, pipeline demo).
DEMO_OUT ?= runs/demo
DEMO_SIZE ?= 256x192
DEMO_VIEWS ?= 10
DEMO_K ?= 6
DEMO_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); if [ "$$n" -ge 2 ]; then echo 2; else echo 1; fi)
DEMO_DATA := $(DEMO_OUT)/llff_like
DEMO_EVAL := $(DEMO_OUT)/eval
demo: $(STAMP)
	test -f $(DEMO_DATA)/split.json || $(VENV)/bin/data-synth render llff_like --out $(DEMO_DATA) --size $(DEMO_SIZE) --views $(DEMO_VIEWS)
	$(VENV)/bin/denoise-gs eval $(DEMO_DATA) --out $(DEMO_EVAL) --preset fast --seeds 1 --views $(DEMO_K) \
		--methods instantsplat product --workers $(DEMO_WORKERS)
	@echo
	@echo "pipeline report:   $(DEMO_EVAL)/runs/llff_like/seed0/product/report.md"
	@echo "evaluation report: $(DEMO_EVAL)/results.md"

demo-eval: demo
	$(VENV)/bin/denoise-gs eval $(DEMO_DATA) --out $(DEMO_EVAL) --preset fast --seeds 1 --views $(DEMO_K) \
		--methods 3dgs_gt_poses instantsplat nlm_instantsplat n2v_round1 denoise_gs denoise_gs_fused product \
		--workers $(DEMO_WORKERS)
	@echo
	@echo "evaluation report: $(DEMO_EVAL)/results.md"

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) .tools .pytest_cache
