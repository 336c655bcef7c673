"""Aggregation over seeds and the results files."""

from __future__ import annotations

import json
import math
from dataclasses import asdict

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


def test_a_method_that_failed_on_a_seed_is_not_ranked_on_the_other_seeds():
    """B fails on seed 0, the hard one, and is behind A on both seeds they share: its mean over the easy seeds
    (24.00) is above A's over all three (21.67), but the table does not mark it best, and says it is over
    two seeds of three."""
    from eval.results import results_markdown

    nan = float("nan")
    rows = [RunScores("s", "A", 0, 15.0, 0.5, 0.5), RunScores("s", "B", 0, nan, nan, nan, error="refused"),
            *(RunScores("s", m, seed, v, 0.7, 0.3) for seed in (1, 2) for m, v in (("A", 25.0), ("B", 24.0)))]
    text = results_markdown(rows)
    assert "| A | 21.67 ± 5.77 |" in text
    assert "| B | 24.00 ± 0.00 (2 of 3 seeds) |" in text and "**" not in text
    assert "- B, seed 0: refused" in text
    # Every method on the same seeds (the failed seed left out of both): ranked as usual.
    same = [r for r in rows if r.seed != 0]
    assert "| A | **25.00 ± 0.00** |" in results_markdown(same)


def test_a_bar_over_fewer_seeds_says_so(tmp_path):
    """The bar chart marks the same shortfall as the table (B failed on one seed of three)."""
    from eval.results import plot_bars, seed_shortfalls

    nan = float("nan")
    rows = [RunScores("s", "A", 0, 15.0, 0.5, 0.5), RunScores("s", "B", 0, nan, nan, nan, error="refused"),
            *(RunScores("s", m, seed, v, 0.7, 0.3) for seed in (1, 2) for m, v in (("A", 25.0), ("B", 24.0)))]
    assert seed_shortfalls(rows, "psnr_db") == {("s", "B"): "2/3"}
    assert seed_shortfalls([r for r in rows if r.seed != 0], "psnr_db") == {}
    assert plot_bars(rows, tmp_path / "bars.png").stat().st_size > 0


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


def _same(a, b):
    """Rows equal field by field, NaN equal to NaN (RunScores' own == compares NaN unequal)."""
    return json.dumps([asdict(r) for r in a], sort_keys=True) == json.dumps([asdict(r) for r in b], sort_keys=True)


def test_earlier_rows_are_carried_only_with_the_same_settings(tmp_path):
    from eval.results import carried_rows, merge_rows

    settings = {"scene": "llff_like", "preset": "default", "splat_iters": None, "code": "abc"}
    rows = _rows()
    rows[0] = RunScores("llff_like", "instantsplat", 0, 20.0, 0.5, 0.4, per_view={"v0": {"psnr_db": 20.0,
                                                                                         "lpips": float("nan")}})
    write_results(tmp_path, rows, settings=settings)

    # Same settings: every row back (NaN metrics and per-view ones included), minus the runs made again.
    kept = carried_rows(tmp_path, dict(settings), rerun=set())
    assert kept.note == "" and _same(kept.rows, rows)
    kept = carried_rows(tmp_path, settings, rerun={("llff_like", "denoise_gs", 1), ("poisson", "denoise_gs", 0)})
    assert [(r.method, r.seed) for r in kept.rows] == [("instantsplat", 0), ("denoise_gs", 0),
                                                        ("instantsplat", 1), ("instantsplat", 2), ("denoise_gs", 2)]
    # A new run of a carried key replaces it; new keys come after the earlier rows.
    new = [RunScores("llff_like", "denoise_gs", 1, 30.0, 0.8, 0.1), RunScores("llff_like", "oracle", 0, 31.0, 0.9, 0.1)]
    merged = merge_rows(kept.rows, new)
    assert [(r.method, r.seed, r.psnr_db) for r in merged][-2:] == [("denoise_gs", 1, 30.0), ("oracle", 0, 31.0)]
    assert len({(r.scene, r.method, r.seed) for r in merged}) == len(merged) == 7

    # Other settings (or none recorded, or an unreadable file): nothing kept, and the note says why.
    other = carried_rows(tmp_path, {**settings, "preset": "fast"}, rerun=set())
    assert other.rows == () and "preset" in other.note and "scene" not in other.note
    write_results(tmp_path, rows)
    assert carried_rows(tmp_path, settings, set()).rows == ()
    assert "no settings" in carried_rows(tmp_path, settings, set()).note
    assert carried_rows(tmp_path / "nothing_here", settings, set()) == type(other)(())
