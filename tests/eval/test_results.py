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


def test_heldout_grid_from_saved_renders(tmp_path):
    """The figure a reader looks at first: clean | noisy | one render per method, for each held-out view."""
    from eval.evaluate import save_heldout_renders
    from eval.pipeline.validate import DatasetFolder
    from eval.results import plot_heldout_grid
    from mvgeo.common.imageio import read_image, write_image

    rng = np.random.default_rng(0)
    clean = {v: rng.uniform(size=(12, 16, 3)).astype(np.float32) for v in ("view_000", "view_008")}
    for part in ("clean", "images"):
        (tmp_path / part).mkdir()
        for v, img in clean.items():
            write_image(tmp_path / part / f"{v}.png", img, bits=16)
    ds = DatasetFolder(tmp_path, ["view_001"], list(clean), {v: tmp_path / "images" / f"{v}.png" for v in clean},
                       {v: tmp_path / "clean" / f"{v}.png" for v in clean})
    folder = tmp_path / "out" / "heldout" / "llff_like"
    assert plot_heldout_grid(folder, tmp_path / "grid.png") is None  # nothing saved yet
    for method in ("denoise_gs", "instantsplat"):
        save_heldout_renders(folder, method, 0, {v: np.clip(img + 0.05, 0, 1) for v, img in clean.items()}, ds)
    np.testing.assert_allclose(read_image(folder / "_clean" / "view_008.png"), clean["view_008"], atol=1e-4)
    assert (folder / "denoise_gs" / "seed0" / "view_000.png").is_file()
    path = plot_heldout_grid(folder, tmp_path / "grid.png")
    img = read_image(path)
    assert img.shape[0] > 100 and img.shape[1] > img.shape[0]  # 2 rows x 4 columns
    # write_results puts it into results.md for each scene that has saved renders
    _, md = write_results(tmp_path / "out", [RunScores("llff_like", "denoise_gs", 0, 20.0, 0.5, 0.3)], title="t")
    assert "figures/heldout_llff_like.png" in md.read_text()
