"""A real `denoise-gs eval` on a local Ray cluster against the serial run (slow).

In a module of its own: `ray_cluster` runs on a Ray already initialised in the process, and the fast
tests' module-scoped cluster (test_distributed.py) runs tiny stages and a fake scorer in its workers.
With this test in that module and the whole file run, the `--workers 2` rows came from that cluster:
nlm_instantsplat seed 0 "scored" with the fake scorer's numbers (rotation error 23.1 = the sum of the
pose entries, SSIM 0.5, LPIPS 0.3) where the serial alignment refused it."""

from __future__ import annotations

import json
import sys

import pytest

from eval.cli import main


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_real_eval_with_two_workers_scores_as_serial(tmp_path):
    """Two seeds of a real evaluation at a tiny size, serially and with `--workers 2`: identical scores.

    The serial process runs with torch's default threads and each task with one; the N2V training runs
    one torch thread per chunk of a batch (`denoise.parallel`), which makes its network the same in both."""
    ray_module = sys.modules.get("ray")
    assert ray_module is None or not ray_module.is_initialized(), \
        "a Ray is already initialised in this process: `--workers 2` would run on it, not on a cluster of its own"
    args = ["eval", "llff_like", "--preset", "fast", "--size", "128x96", "--scene-views", "8", "--splat-iters",
            "60", "--seeds", "2", "--methods", "nlm_instantsplat", "n2v_round1"]
    assert main([*args, "--out", str(tmp_path / "serial")]) == 0
    assert main([*args, "--out", str(tmp_path / "ray"), "--workers", "2"]) == 0
    serial = json.loads((tmp_path / "serial" / "results.json").read_text())["runs"]
    ray = json.loads((tmp_path / "ray" / "results.json").read_text())["runs"]
    keys = ("scene", "method", "seed", "psnr_db", "ssim", "lpips", "rot_err_deg", "ate", "per_view", "error")
    assert [{k: r[k] for k in keys} for r in ray] == [{k: r[k] for k in keys} for r in serial]
    assert [(r["method"], r["seed"]) for r in ray] == [(m, s) for s in (0, 1) for m in ("nlm_instantsplat",
                                                                                      "n2v_round1")]
    assert any(r["psnr_db"] is not None for r in ray)  # something was scored, not only failed rows
