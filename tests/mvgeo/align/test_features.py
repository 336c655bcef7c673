"""`mvgeo.align.features`: SIFT in our pixel convention, the BLAS matcher against its loop reference, and the
sensitive re-detection rule of `detect_and_match`."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import mvgeo.align.features as features
from mvgeo.align.classical_pairs import ClassicalPairConfig
from mvgeo.align.features import (
    ImageFeatures,
    MatchSet,
    detect_and_match,
    estimate_noise_sigma,
    estimate_noise_sigma_reference,
    extract_features,
    match_features,
    match_features_reference,
)
from mvgeo.align.pairs import PairFailure
from mvgeo.common.deps import cv2


def test_blas_matching_equals_loop_reference(rng):
    base = rng.random((300, 128)).astype(np.float32) * 100
    a = ImageFeatures(np.zeros((300, 2)), base)
    # 200 noisy copies (true matches), 40 near-duplicates of one descriptor (ambiguous: ratio test
    # must reject), 60 unrelated.
    b_desc = np.concatenate([base[:200] + rng.random((200, 128)).astype(np.float32) * 15,
                             np.repeat(base[250:251], 40, axis=0) + rng.random((40, 128)).astype(np.float32),
                             rng.random((60, 128)).astype(np.float32) * 100])
    b = ImageFeatures(np.zeros((300, 2)), b_desc)
    for ratio in (0.6, 0.8, 0.95):
        fast = match_features(a, b, ratio=ratio)
        ref = match_features_reference(a, b, ratio=ratio)
        np.testing.assert_array_equal(fast, ref)
    assert 150 < len(match_features(a, b, ratio=0.8)) <= 200
    # Row blocks of any size (incl. one row, and blocks that do not divide the rows) give the same matches.
    for block in (1, 7, 64, 1000):
        np.testing.assert_array_equal(match_features(a, b, ratio=0.8, block_rows=block),
                                      match_features_reference(a, b, ratio=0.8))
    # Exact ties: two identical rows in a both best match one column; the column's ratio test must
    # reject both (as the loop does), not match that column twice.
    a_tie = ImageFeatures(np.zeros((301, 2)), np.concatenate([base, base[:1]]))
    fast = match_features(a_tie, b, ratio=0.95, block_rows=7)
    np.testing.assert_array_equal(fast, match_features_reference(a_tie, b, ratio=0.95))
    assert 0 not in fast[:, 0] and 300 not in fast[:, 0] and 0 in match_features(a, b, ratio=0.95)[:, 0]
    assert len(match_features(a, ImageFeatures(np.zeros((1, 2)), b_desc[:1]), ratio=0.8)) == 0


def _blobs(H, W, centres_px, sigma_px=3.0):
    """(H, W, 3) float32 image of Gaussian blobs centred at `centres_px` (u, v) in our convention."""
    v, u = np.mgrid[0:H, 0:W] + 0.5  # pixel (row, col) has centre (col + 0.5, row + 0.5)
    img = sum(np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma_px ** 2)) for cu, cv in centres_px)
    return np.repeat((0.1 + 0.8 * img / img.max())[..., None], 3, axis=2).astype(np.float32)


def test_keypoints_are_in_our_pixel_convention():
    """A blob and the same image turned by 180 deg: in our convention pixel p maps to (W, H) - p, so the
    detections of both (the second mapped back) average to the blob's centre, whatever bias the detector
    has (OpenCV's SIFT puts these blobs ~0.26 px down-right, and 0.26 px up-left once turned). OpenCV's
    own convention (pixel centres at integers) would put the average 0.5 px up-left of it."""
    H, W = 96, 128
    centres = [(40.0, 30.0), (90.25, 60.5), (25.5, 70.0)]
    img = _blobs(H, W, centres)
    f = extract_features(img, n_features=100, contrast_threshold=0.01)
    f_turned = extract_features(np.ascontiguousarray(img[::-1, ::-1]), n_features=100, contrast_threshold=0.01)
    back = np.array([W, H]) - f_turned.uv_px
    for c in centres:
        near = f.uv_px[np.linalg.norm(f.uv_px - c, axis=1) < 1.0]
        near_back = back[np.linalg.norm(back - c, axis=1) < 1.0]
        assert len(near) and len(near_back), c
        mean = 0.5 * (near.mean(axis=0) + near_back.mean(axis=0))
        np.testing.assert_allclose(mean, c, atol=0.05)
    assert f.desc.shape == (len(f.uv_px), 128) and f.desc.dtype == np.float32
    empty = extract_features(np.full((H, W, 3), 0.5, np.float32), n_features=100)  # nothing to detect
    assert empty.uv_px.shape == (0, 2) and empty.desc.shape == (0, 128)


def _textured(H, W, seed=0):
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur((rng.random((H, W)) * 255).astype(np.float32), (0, 0), 2.0)
    g = cv2.normalize(g, None, 0.0, 1.0, cv2.NORM_MINMAX)
    return np.repeat(g[..., None], 3, axis=2).astype(np.float32)


def test_matched_pixels_of_a_shifted_crop_differ_by_the_shift():
    """Two crops of one textured image, (dx, dy) = (7, 4) px apart: `MatchSet.pixels` of the pair are the
    same scene points, so view j's pixel = view i's pixel - shift."""
    big = _textured(140, 180)
    a, b = big[10:106, 20:148], big[14:110, 27:155]  # b starts 7 columns and 4 rows later
    cfg = ClassicalPairConfig(sift_features=1000, min_matches=10, sensitive_below_noise=0.0)
    with ThreadPoolExecutor(2) as pool:
        ms = detect_and_match([a, b], [(0, 1)], cfg, pool)
    assert isinstance(ms, MatchSet) and not ms.sensitive and ms.image_hw == (96, 128)
    u1, u2 = ms.pixels(0, 1)
    assert len(u1) >= 50
    d = u1 - u2 - np.array([7.0, 4.0])
    assert np.median(np.linalg.norm(d, axis=1)) < 0.1


def _fake_runs(monkeypatch, graphs):
    """`_detect_and_match_once` returning, per contrast threshold, the matched pairs in `graphs`."""
    calls = []

    def once(images, pairs, pool, *, n_features, ratio, min_matches, contrast, blur):
        calls.append(contrast)
        matched = graphs[contrast]
        feats = [ImageFeatures(np.zeros((1, 2)), np.zeros((1, 128), np.float32)) for _ in images]
        matches = {ij: np.zeros((min_matches, 2), np.int64) for ij in matched}
        fails = [PairFailure(i, j, "few") for i, j in pairs if (i, j) not in matched]
        return feats, matches, fails

    monkeypatch.setattr(features, "_detect_and_match_once", once)
    return calls


@pytest.mark.parametrize("case", ["connected", "fallback_connects", "fallback_worse", "fallback_tie_more_pairs",
                                  "fallback_tie_same_pairs", "fallback_off"])
def test_sensitive_detection_only_when_the_match_graph_is_cut_and_kept_only_if_better(monkeypatch, case):
    cfg = ClassicalPairConfig(fallback_sift=case != "fallback_off", sensitive_below_noise=0.0)
    images = [np.zeros((8, 8, 3), np.float32)] * 4
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    default, sensitive = cfg.sift_contrast_threshold, cfg.fallback_contrast_threshold
    graphs = {
        "connected": {default: [(0, 1), (1, 2), (2, 3)], sensitive: pairs},
        "fallback_connects": {default: [(0, 1), (2, 3)], sensitive: [(0, 1), (1, 2), (2, 3)]},
        "fallback_worse": {default: [(0, 1), (2, 3)], sensitive: [(0, 1)]},  # 2 pieces -> 3
        # The same number of pieces: the run with more matched pairs is kept.
        "fallback_tie_more_pairs": {default: [(0, 1), (2, 3)], sensitive: [(0, 1), (0, 2), (1, 2)]},
        "fallback_tie_same_pairs": {default: [(0, 1), (2, 3)], sensitive: [(0, 2), (1, 3)]},
        "fallback_off": {default: [(0, 1)], sensitive: pairs},
    }[case]
    calls = _fake_runs(monkeypatch, graphs)
    ms = detect_and_match(images, pairs, cfg, pool=None)
    tried = case not in ("connected", "fallback_off")
    assert calls == ([default, sensitive] if tried else [default])
    kept_sensitive = case in ("fallback_connects", "fallback_tie_more_pairs")
    assert ms.sensitive == kept_sensitive
    assert sorted(ms.matches) == sorted(graphs[sensitive if kept_sensitive else default])
    assert sorted((f.i, f.j) for f in ms.failures) == sorted(set(pairs) - set(ms.matches))


def test_noise_estimate_equals_the_explicit_sum_and_recovers_the_noise(rng):
    """Immerkaer's estimate: the filter2D path against the explicit 3x3 sum; on a smooth image (a quadratic
    ramp, to which the mask is blind) with Gaussian noise it recovers sigma (mean |N(0, s)| = s sqrt(2 / pi),
    the mask's gain 6: exact in expectation; 10 % covers the sampling error of 60k pixels, ~1 %)."""
    H, W = 240, 256
    yy, xx = np.mgrid[0:H, 0:W] / 256.0
    smooth = 0.3 + 0.2 * xx + 0.1 * yy**2
    for sigma in (0.0, 0.01, 0.05):
        img = (smooth + rng.normal(scale=sigma, size=(H, W))).astype(np.float32)
        est = estimate_noise_sigma(img)
        assert est == pytest.approx(estimate_noise_sigma_reference(img), rel=1e-5, abs=1e-7)
        assert est == pytest.approx(sigma, rel=0.1, abs=1e-4)
    rgb = np.repeat(smooth[..., None], 3, axis=2).astype(np.float32)
    assert estimate_noise_sigma(rgb) < 1e-4  # a noise-free RGB image (through the gray conversion)


@pytest.mark.parametrize("sigma", [0.0, 0.03])
def test_clean_images_get_the_sensitive_detection_from_the_start(monkeypatch, rng, sigma):
    """Below `sensitive_below_noise` (3/255) one detection, with the fallback's settings; above it the
    default detection (and no fallback: here its graph is connected)."""
    cfg = ClassicalPairConfig()
    H, W = 32, 32
    yy, xx = np.mgrid[0:H, 0:W] / 32.0
    base = np.repeat((0.4 + 0.2 * xx + 0.1 * yy)[..., None], 3, axis=2)
    images = [(base + rng.normal(scale=sigma, size=base.shape)).astype(np.float32) for _ in range(3)]
    pairs = [(0, 1), (0, 2), (1, 2)]
    default, sensitive = cfg.sift_contrast_threshold, cfg.fallback_contrast_threshold
    calls = _fake_runs(monkeypatch, {default: pairs, sensitive: pairs})
    ms = detect_and_match(images, pairs, cfg, pool=None)
    clean = sigma == 0.0
    assert calls == ([sensitive] if clean else [default])
    assert ms.sensitive == clean
