"""`denoise.grouped_wiener`: the grouped Wiener step against a group-by-group reference, and what it must do."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from denoise.grouped_wiener import GroupedWienerConfig, _wiener_rows, grouped_wiener, pass_configs, search_offsets
from denoise.wiener import OPPONENT, dct_wiener


def _reference(noisy: np.ndarray, pilot: np.ndarray, std: np.ndarray, cfg: GroupedWienerConfig) -> np.ndarray:
    """One reference patch at a time, distances by explicit slicing, the Wiener estimate by a dense solve:
    the definition the fast path vectorises. Colour photos ``(H, W, 3)``, `std` per pixel and channel."""
    H, W, C = noisy.shape
    p, rad, n = cfg.patch_px, cfg.search_radius_px, cfg.group_size
    y, b = noisy @ OPPONENT.T, pilot @ OPPONENT.T
    var = np.maximum((std ** 2) @ (OPPONENT ** 2).T, 1e-6)
    clipped = (noisy <= 0) | (noisy >= 1)
    rows = sorted(set(range(0, H - p + 1, cfg.stride_px)) | {H - p})
    cols = sorted(set(range(0, W - p + 1, cfg.stride_px)) | {W - p})
    num, den = np.zeros((H, W, C)), np.zeros((H, W))
    for r in rows:
        for c in cols:
            cands = []
            for dy in range(-rad, rad + 1):
                for dx in range(-rad, rad + 1):
                    rr, cc = r + dy, c + dx
                    if 0 <= rr <= H - p and 0 <= cc <= W - p:
                        diff = b[r:r + p, c:c + p] - b[rr:rr + p, cc:cc + p]
                        dist = -1.0 if dy == dx == 0 else float(np.sum(diff ** 2))
                        cands.append((dist, rr, cc))
            group = [(rr, cc) for _, rr, cc in sorted(cands)[:n]]
            Y = np.stack([y[rr:rr + p, cc:cc + p].ravel() for rr, cc in group])
            B = np.stack([b[rr:rr + p, cc:cc + p].ravel() for rr, cc in group])
            share = np.mean([clipped[rr:rr + p, cc:cc + p] for rr, cc in group])
            S = np.diag(np.tile(np.mean([var[rr:rr + p, cc:cc + p] for rr, cc in group], axis=(0, 1, 2)), p * p))
            cov = np.cov(B, rowvar=False)
            m = B.mean(0) if share > cfg.clipped_share else Y.mean(0)
            X = m + (cov @ np.linalg.solve(cov + S, (Y - m).T)).T
            for (rr, cc), x in zip(group, X, strict=True):
                num[rr:rr + p, cc:cc + p] += x.reshape(p, p, C)
                den[rr:rr + p, cc:cc + p] += 1
    return (num / den[..., None]) @ OPPONENT


def _photo(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random colour photo with bright parts (so some noisy values clip), and its clipped noisy copy."""
    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W] / 4.0
    base = 0.55 + 0.45 * np.sin(xx + rng.uniform(0, 6)) * np.cos(0.8 * yy)
    clean = np.clip(np.stack([base, 0.8 * base + 0.1, 1.0 - 0.7 * base], axis=-1), 0, 1)
    return clean, np.clip(clean + rng.normal(0, sigma, clean.shape), 0, 1)


@pytest.mark.parametrize("shape,patch,radius,group,stride", [((14, 13), 3, 2, 6, 2), ((11, 16), 4, 3, 10, 3),
                                                             ((9, 9), 2, 1, 4, 1),
                                                             ((12, 11), 2, 3, 14, 2)])  # n >= d: the d x d solve
def test_the_fast_path_matches_the_group_by_group_reference(shape, patch, radius, group, stride):
    rng = np.random.default_rng(shape[0])
    clean, noisy = _photo(rng, shape, 0.15)
    pilot = clean + rng.normal(0, 0.02, clean.shape)  # a pilot close to the clean photo, no ties in distances
    std = rng.uniform(0.05, 0.2, noisy.shape)  # per pixel and channel (signal-dependent noise)
    cfg = GroupedWienerConfig(patch_px=patch, search_radius_px=radius, group_size=group, stride_px=stride,
                              clipped_share=0.05, groups_per_chunk=7)  # several chunks
    assert ((noisy == 0) | (noisy == 1)).mean() > 0.02  # the clipped-share rule is exercised
    got = grouped_wiener(noisy, pilot, std, cfg)
    ref = _reference(noisy, pilot, std, cfg)
    # float32 groups against a float64 reference: values ~1, errors ~1e-6.
    np.testing.assert_allclose(got, ref, atol=2e-5)


@pytest.mark.parametrize("n,d", [(6, 27), (40, 75), (39, 40)])
def test_the_groups_n_dimensional_solve_is_the_d_dimensional_wiener_gain(n, d):
    """`_wiener_rows` with fewer patches than dimensions (the push-through identity) against
    ``(Y - m) (C + S)^-1 C`` solved in float64 by `np.linalg.solve`; noise variances from 1e-6 (the floor)
    to 0.04, pilot patches with a spread like a photo's (0.3)."""
    rng = np.random.default_rng(n + d)
    B = rng.normal(0.5, 0.3, (5, n, d))
    Bc = B - B.mean(axis=1, keepdims=True)
    Yc = rng.normal(0, 0.2, (5, n, d))
    S = 10.0 ** rng.uniform(-6, np.log10(0.04), (5, d))
    got = _wiener_rows(*(torch.from_numpy(a.astype(np.float32)) for a in (Yc, Bc, S))).numpy()
    for g in range(5):
        C = Bc[g].T @ Bc[g] / (n - 1)
        ref = (np.linalg.solve(C + np.diag(S[g]), C).T @ Yc[g].T).T  # (Y - m) (C + S)^-1 C
        # float32 against float64, through a system of condition number up to ~1e6 (S at its floor): the
        # rows' values are ~0.2-1 and agree to 2e-3 relative; the d x d float32 solve does no better.
        np.testing.assert_allclose(got[g], ref, atol=2e-3 * np.abs(ref).max())


def test_one_std_for_all_pixels_is_the_constant_map_and_gray_is_one_channel():
    rng = np.random.default_rng(3)
    clean, noisy = _photo(rng, (15, 17), 0.1)
    cfg = GroupedWienerConfig(patch_px=3, search_radius_px=2, group_size=8, stride_px=2)
    np.testing.assert_array_equal(grouped_wiener(noisy, clean, 0.1, cfg),
                                  grouped_wiener(noisy, clean, np.full(noisy.shape, 0.1), cfg))
    gray = grouped_wiener(noisy[..., 0], clean[..., 0], 0.1, cfg)
    assert gray.shape == noisy.shape[:2] and gray.dtype == np.float32
    # Gray: each group's filter on one channel; as accurate as the pilot's statistics allow.
    assert np.mean((gray - clean[..., 0]) ** 2) < 0.5 * np.mean((noisy[..., 0] - clean[..., 0]) ** 2)


def test_a_noise_free_photo_comes_back_as_it_is():
    rng = np.random.default_rng(4)
    _, photo = _photo(rng, (20, 18), 0.1)
    out = grouped_wiener(photo, photo, 0.0, GroupedWienerConfig(patch_px=3, search_radius_px=3, group_size=12))
    np.testing.assert_allclose(out, photo, atol=1e-4)


def test_grouping_beats_the_blockwise_dct_step_on_a_repetitive_texture():
    # A periodic colour texture (bricks, tiles): each patch has many noisy twins in the search window,
    # which the grouped step averages and the block-by-block DCT step cannot. Pilot: the DCT step with the
    # noisy photo as its own pilot (the plain empirical Wiener filter); then each step once more with that
    # pilot, at the true sigma. The grouped step must cut the pilot's error by a quarter (0.68x measured)
    # and beat the DCT step's second pass (0.87x of its error measured).
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:64, 0:64]
    tile = rng.uniform(0.2, 0.8, (4, 4, 3))  # 25 exact twins of each patch within the default +-10 px
    clean = tile[yy % 4, xx % 4]
    noisy = np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1)
    pilot = dct_wiener(noisy, noisy, 0.1)
    mse = {k: float(np.mean((x - clean) ** 2)) for k, x in [
        ("noisy", noisy), ("pilot", pilot), ("dct", dct_wiener(noisy, pilot, 0.1)),
        ("grouped", grouped_wiener(noisy, pilot, 0.1))]}
    assert mse["pilot"] < mse["noisy"], mse
    assert mse["grouped"] < 0.75 * mse["pilot"] and mse["grouped"] < mse["dct"], mse


def test_photos_smaller_than_the_search_window_or_a_patch():
    rng = np.random.default_rng(6)
    clean, noisy = _photo(rng, (7, 9), 0.1)
    out = grouped_wiener(noisy, clean, 0.1, GroupedWienerConfig(search_radius_px=10, group_size=40))
    assert out.shape == noisy.shape and np.isfinite(out).all()
    assert np.mean((out - clean) ** 2) < np.mean((noisy - clean) ** 2)
    tiny = grouped_wiener(noisy[:3, :3], clean[:3, :3], 0.1)  # smaller than a 5-px patch: the pilot
    np.testing.assert_allclose(tiny, clean[:3, :3], atol=1e-6)


def test_search_offsets_put_zero_in_the_middle():
    off = search_offsets(2)
    assert off.shape == (25, 2) and tuple(off[len(off) // 2]) == (0, 0)


@pytest.mark.parametrize("kwargs", [dict(patch_px=0), dict(search_radius_px=-1), dict(group_size=1),
                                    dict(search_radius_px=1, group_size=10), dict(stride_px=0),
                                    dict(clipped_share=1.5), dict(groups_per_chunk=0), dict(passes=0),
                                    dict(passes=2, search_radius_px=3, later_group_size=80)])
def test_invalid_configs_are_refused(kwargs):
    with pytest.raises(ValueError, match="GroupedWienerConfig"):
        GroupedWienerConfig(**kwargs)


def test_mismatched_shapes_are_refused():
    with pytest.raises(ValueError, match="must both be"):
        grouped_wiener(np.zeros((8, 8, 3)), np.zeros((8, 9, 3)), 0.1)


def test_a_dark_clipped_photo_is_filtered_in_the_clipped_domain():
    # A dark texture (values 0.01-0.1) under sigma 0.1: about half of the noisy values are clipped to 0, their
    # mean is biased upwards. The denoise stage filters such a photo where its values live (the pilot mapped to
    # the clipped mean, the clipped noise's std) and undoes the bias after: better than its pilot (0.34x its
    # error measured). The clean-value pilot against the clipped noisy patches is biased (7x the pilot's).
    import torch

    from denoise.self_supervised import _grouped, _undo_clipping

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:48, 0:48] / 3.0
    base = 0.04 + 0.03 * np.sin(xx) * np.cos(0.7 * yy)
    clean = np.stack([base, base, 1.5 * base], -1).astype(np.float32)
    noisy = np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1).astype(np.float32)
    pilot = np.clip(clean + rng.normal(0, 0.01, clean.shape), 0, 1).astype(np.float32)
    sigma = [torch.tensor(0.1)]
    mse = {}
    for clipped_domain in (False, True):
        out = _grouped([noisy], [pilot], sigma, 0.0, GroupedWienerConfig(), clipped_domain=clipped_domain)
        mse[clipped_domain] = float(np.mean((_undo_clipping([noisy], out, sigma, 0.0)[0] - clean) ** 2))
    mse_pilot = float(np.mean((pilot - clean) ** 2))
    assert mse[True] < 0.6 * mse_pilot < mse[False], (mse, mse_pilot)


def test_the_passes_after_the_first_take_the_later_group_size():
    cfg = GroupedWienerConfig(group_size=30, passes=3, later_group_size=70, patch_px=3)
    assert [(c.group_size, c.passes, c.patch_px) for c in pass_configs(cfg)] == [(30, 1, 3), (70, 1, 3), (70, 1, 3)]
    assert pass_configs(GroupedWienerConfig()) == [GroupedWienerConfig()]
    # one pass never reads later_group_size: a small search window may leave it out of range
    assert len(pass_configs(GroupedWienerConfig(search_radius_px=3, group_size=12))) == 1


def test_two_passes_are_the_step_run_again_on_its_own_output():
    """The denoise stage's passes (`_then_grouped`) against the step written out twice by hand: grouped, the
    clipping correction, grouped again with the later group size on that output, the correction again. On a
    repetitive texture the second pass, with a better pilot, lowers the error further."""
    import torch

    from denoise.self_supervised import _grouped, _then_grouped, _undo_clipping

    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:40, 0:40]
    tile = rng.uniform(0.2, 0.8, (4, 4, 3))
    clean = tile[yy % 4, xx % 4].astype(np.float32)
    noisy = np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1).astype(np.float32)
    pilot = dct_wiener(noisy, noisy, 0.1).astype(np.float32)
    sigma = [torch.tensor(0.1)]
    cfg = GroupedWienerConfig(patch_px=3, search_radius_px=4, group_size=12, passes=2, later_group_size=24)
    got = _then_grouped([noisy], [pilot], sigma, 0.0, True, cfg)[0]
    once = _grouped([noisy], _undo_clipping([noisy], [pilot], sigma, 0.0), sigma, 0.0,
                    GroupedWienerConfig(patch_px=3, search_radius_px=4, group_size=12), clipped_domain=True)
    once = _undo_clipping([noisy], once, sigma, 0.0)
    twice = _grouped([noisy], once, sigma, 0.0, GroupedWienerConfig(patch_px=3, search_radius_px=4, group_size=24),
                     clipped_domain=True)
    twice = _undo_clipping([noisy], twice, sigma, 0.0)[0]
    np.testing.assert_array_equal(got, twice)
    mse_once, mse_twice = (float(np.mean((x - clean) ** 2)) for x in (once[0], twice))
    assert mse_twice < mse_once, (mse_once, mse_twice)


def test_a_gray_photo_read_as_rgb_is_filtered_as_the_gray_photo():
    """Three equal channels hold the same noise, not the independent noise of the opponent space: such a photo is
    filtered as the gray one, its pilot's channels averaged and the noise std's RMS over the channels taken."""
    rng = np.random.default_rng(9)
    clean, _ = _photo(rng, (20, 22), 0.1)
    gray = clean[..., 0]
    noisy = gray + rng.normal(0, 0.1, gray.shape)
    pilot = gray + rng.normal(0, 0.02, gray.shape)
    rgb = np.repeat(noisy[..., None], 3, axis=2)
    prgb = np.repeat(pilot[..., None], 3, axis=2) + np.array([0.0, 0.01, -0.01])
    cfg = GroupedWienerConfig(patch_px=3, search_radius_px=3, group_size=10, stride_px=2)
    want = np.repeat(grouped_wiener(noisy, pilot, 0.1, cfg)[..., None], 3, axis=2)
    np.testing.assert_allclose(grouped_wiener(rgb, prgb, 0.1, cfg), want, atol=1e-6)
    np.testing.assert_allclose(grouped_wiener(rgb, prgb, np.full(rgb.shape, 0.1), cfg), want, atol=1e-6)
