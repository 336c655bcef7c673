"""Filling stereo depth holes by harmonic interpolation of the inverse depth (`mvgeo.align.hole_fill`)."""

import numpy as np
import pytest

from mvgeo.align.hole_fill import HoleFillConfig, fill_depth_holes, harmonic_fill, wide_holes
from mvgeo.common.deps import cv2

H, W = 96, 128
K = np.array([[100.0, 0.0, W / 2], [0.0, 100.0, H / 2], [0.0, 0.0, 1.0]])


def _plane_depth(normal, offset):
    """z-depth of the plane n.X = offset seen through every pixel (pixel centres at +0.5)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1
    return offset / (rays @ np.asarray(normal, float))


def test_a_plane_around_a_hole_is_continued():
    """Inverse depth is affine in the pixel coordinates on a plane: a smooth interpolation reproduces it."""
    z = _plane_depth([0.0, -0.4, 1.0], 4.0)  # a floor receding upwards, depth 3-6
    hole = np.zeros((H, W), bool)
    hole[30:70, 40:100] = True
    d = np.where(hole, np.nan, z)
    c = np.where(hole, 1.0, 8.0)
    # min_width 0: every hole (the opening is tested below); this hole is 40 px wide anyway.
    (df,), (cf,), (mask,) = fill_depth_holes([d], [c], HoleFillConfig(fill_conf=2.5, min_width=0.0))
    assert np.array_equal(mask, hole)
    np.testing.assert_array_equal(df[~hole], z[~hole])  # measured depth untouched
    np.testing.assert_array_equal(cf[~hole], 8.0)
    assert np.all(cf[hole] == 2.5)
    # Affine functions are harmonic: the plane is continued exactly (up to the LU solve's rounding).
    np.testing.assert_allclose(df[hole], z[hole], rtol=1e-9)


def test_a_plane_is_continued_to_the_image_border():
    """The border is a zero-normal-derivative boundary: exact for a plane whose inverse depth does not
    change across it (here: along u, at the right border)."""
    z = _plane_depth([0.0, -0.4, 1.0], 4.0)
    hole = np.zeros((H, W), bool)
    hole[30:70, 40:] = True
    (df,), _, (mask,) = fill_depth_holes([np.where(hole, np.nan, z)], [np.ones((H, W))], HoleFillConfig(min_width=0.0))
    assert np.array_equal(mask, hole)
    np.testing.assert_allclose(df[hole], z[hole], rtol=1e-9)


def _harmonic_reference(values, known, sweeps=20000):
    """Gauss-Seidel sweeps of 'each unknown pixel = mean of its in-image 4-neighbours' (slow, obvious)."""
    out = np.where(known, values, 0.0).astype(float)
    Hs, Ws = out.shape
    todo = list(zip(*np.nonzero(~known), strict=True))
    for _ in range(sweeps):
        delta = 0.0
        for r, c in todo:
            nb = [out[rr, cc] for rr, cc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1))
                  if 0 <= rr < Hs and 0 <= cc < Ws]
            new = sum(nb) / len(nb)
            delta = max(delta, abs(new - out[r, c]))
            out[r, c] = new
        if delta < 1e-13:
            break
    return out


def test_harmonic_fill_matches_gauss_seidel_reference(rng):
    values = rng.uniform(0.1, 1.0, (9, 11))
    known = rng.uniform(size=(9, 11)) < 0.4
    known[0, 0] = True
    np.testing.assert_allclose(harmonic_fill(values, known), _harmonic_reference(values, known), atol=1e-10)
    with pytest.raises(ValueError, match="at least one known pixel"):
        harmonic_fill(values, np.zeros((9, 11), bool))


def test_a_hole_between_two_depths_is_filled_within_them():
    """No overshoot: the filled depth stays between the depths around the hole."""
    d = np.full((H, W), 2.0)
    d[:, W // 2:] = 5.0
    d[20:80, 50:80] = np.nan
    (df,), _, (mask,) = fill_depth_holes([d], [np.ones((H, W)) * 5], HoleFillConfig(min_width=0.0))
    assert mask.sum() == 60 * 30
    assert np.all(np.isfinite(df)) and df[mask].min() >= 2.0 - 1e-6 and df[mask].max() <= 5.0 + 1e-6


def test_disabled_nearly_empty_and_full_maps_are_left_alone():
    z = _plane_depth([0.0, 0.0, 1.0], 3.0)
    d = z.copy()
    d[10:20, 10:20] = np.nan
    (d_off,), (c_off,), (m_off,) = fill_depth_holes([d], [np.ones((H, W))], HoleFillConfig(enabled=False))
    assert not m_off.any() and np.isnan(d_off[10:20, 10:20]).all()
    sparse = np.full((H, W), np.nan)
    sparse[0:5, 0:5] = 3.0  # 0.2 % of the pixels: below min_valid_fraction
    (d_sp,), _, (m_sp,) = fill_depth_holes([sparse], [np.ones((H, W))])
    assert not m_sp.any() and np.isnan(d_sp).sum() == H * W - 25
    (d_full,), _, (m_full,) = fill_depth_holes([z], [np.ones((H, W))])
    assert not m_full.any() and np.array_equal(d_full, z)


def _opening_reference(hole, r):
    """Pixels covered by some placement of the radius-r disc (OpenCV's ellipse kernel) whose in-image
    pixels all lie in `hole` (slow, obvious)."""
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)).astype(bool)
    offs = np.argwhere(disc) - r
    Hh, Wh = hole.shape
    out = np.zeros_like(hole)
    for cy in range(Hh):
        for cx in range(Wh):
            ys, xs = cy + offs[:, 0], cx + offs[:, 1]
            inside = (ys >= 0) & (ys < Hh) & (xs >= 0) & (xs < Wh)
            if hole[ys[inside], xs[inside]].all():
                out[ys[inside], xs[inside]] = True
    return out & hole


def test_wide_holes_is_the_opening_by_a_disc(rng):
    hole = np.zeros((40, 50), bool)
    hole[5:25, 5:30] = True  # wide: kept (its corners are rounded off)
    hole[30:33, 0:50] = True  # a 3 px strip: dropped
    hole[0:40, 46:50] = True  # 4 px wide along the border: the outside counts as hole, so it is kept
    hole |= rng.uniform(size=hole.shape) < 0.05  # speckle: dropped
    r = 3  # min_width 0.12 of the long side 50
    got = wide_holes(hole, 0.12)
    np.testing.assert_array_equal(got, _opening_reference(hole, r))
    assert got[15, 17] and not got[31, 20] and got[20, 48]
    assert np.array_equal(wide_holes(hole, 0.0), hole)


def test_narrow_holes_are_not_filled():
    z = _plane_depth([0.0, 0.0, 1.0], 3.0)
    d = z.copy()
    d[40:43, :] = np.nan  # 3 px strip
    d[10:60, 70:120] = np.nan  # 50 px square
    (df,), _, (mask,) = fill_depth_holes([d], [np.ones((H, W))], HoleFillConfig(min_width=0.05))  # 6.4 px
    assert not mask[40:43, :60].any() and np.isnan(df[41, 30])
    assert mask[12:58, 72:118].all()


def test_the_views_are_filled_alike_on_any_number_of_threads(rng):
    """Three views with wide holes of different shapes and planes of different slopes: one thread and
    several give the same depths, confidences and masks, in the views' order."""
    H, W = 40, 48
    yy, xx = np.mgrid[0:H, 0:W]
    depth, conf = [], []
    for k in range(3):
        d = 2.0 + 0.01 * xx + 0.02 * k * yy + 0.05 * rng.standard_normal((H, W))
        d[5 + 3 * k:25 + 2 * k, 8:30 - k] = np.nan
        depth.append(d)
        conf.append(rng.uniform(3, 6, (H, W)))
    cfg = HoleFillConfig(min_width=0.1)
    one = fill_depth_holes(depth, conf, cfg, workers=1)
    many = fill_depth_holes(depth, conf, cfg, workers=3)
    assert all(m.any() for m in one[2])  # every view has filled pixels: the test can fail
    for a, b in zip(one, many, strict=True):
        assert all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True))
