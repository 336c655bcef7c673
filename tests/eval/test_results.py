"""Aggregation over seeds and the results files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from eval.results import RunScores, summarise, write_results


def _rows():
    rows = []
    for seed, (a, b) in enumerate([(20.0, 25.0), (22.0, 27.0), (21.0, 26.0)]):
        rows.append(RunScores("llff_like", "instantsplat", seed, a, 0.5, 0.4, rot_err_deg=1.0, ate=0.01,
                              seconds=10.0))
        rows.append(RunScores("llff_like", "denoise_gs", seed, b, 0.7, 0.2, seconds=30.0))
    rows.append(RunScores("poisson", "denoise_gs", 0, 24.0, 0.6, 0.3))
    return rows


def test_summary_mean_and_sample_std():
    s = summarise(_rows())
    c = s["llff_like"]["instantsplat"]["psnr_db"]
    assert c.mean == pytest.approx(21.0) and c.n == 3
    assert c.std == pytest.approx(np.std([20.0, 22.0, 21.0], ddof=1))  # sample std, = 1.0
    assert s["llff_like"]["denoise_gs"]["ate"].n == 0  # all NaN: not applicable
    one = s["poisson"]["denoise_gs"]["psnr_db"]
    assert one.n == 1 and math.isnan(one.std)


def test_files(tmp_path):
    js, md = write_results(tmp_path, _rows(), title="t")
    data = json.loads(js.read_text())  # strict JSON: NaN became null
    assert len(data["runs"]) == 7 and data["runs"][1]["ate"] is None
    text = md.read_text()
    assert "| denoise_gs | **26.00 ± 1.00** |" in text  # best PSNR in bold, mean ± std
    assert "21.00 ± 1.00" in text and "n/a" in text
    for m in ("psnr_db", "ssim", "lpips"):
        assert (tmp_path / "figures" / f"{m}.png").stat().st_size > 1000
