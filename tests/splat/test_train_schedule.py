"""The trainer's coarse-to-fine schedule and its per-sub-step timings.

References: a slow per-pixel box filter for the area downsampling, a full-size render shrunk with
that filter for the rescaled intrinsics, and densification statistics at full size for the coarse
ones. Scenes are tiny and self-rendered; no external data.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import splat.train as train_mod
from mvgeo.camera import Camera
from mvgeo.common.errors import ConfigError
from splat.cameras_torch import pinhole_K
from splat.densify import DensifyConfig, DensifyState, accumulate
from splat.gaussian_model import GaussianModel
from splat.losses import photometric_loss
from splat.rasterize import RasterConfig
from splat.render import render_views
from splat.train import OPTIMIZE_SUBSTEPS, TrainConfig, coarse_size_wh, downsample_area, train_gaussians
from tests.splat.scenes import look_at_cam_from_world


def _box_reference(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Output pixel (r, c) = mean of the input over [c, c+1) * W/width x [r, r+1) * H/height, each input
    pixel weighted by its overlap with that footprint (a direct double loop)."""
    h0, w0 = img.shape[:2]
    sx, sy = w0 / width, h0 / height

    def weights(n_out, n_in, step):
        wts = np.zeros((n_out, n_in))
        for j in range(n_out):
            lo, hi = j * step, (j + 1) * step
            for i in range(n_in):
                wts[j, i] = max(0.0, min(hi, i + 1) - max(lo, i))
        return wts / step

    out = np.zeros((height, width, img.shape[2]))
    wy, wx = weights(height, h0, sy), weights(width, w0, sx)
    for r in range(height):
        for c in range(width):
            out[r, c] = np.einsum("i,j,ijk->k", wy[r], wx[c], img.astype(np.float64))
    return out


@pytest.mark.parametrize(("size_in", "size_out"), [((12, 8), (6, 4)), ((13, 10), (5, 4)), ((7, 9), (3, 7))])
def test_downsample_area_matches_box_reference(size_in, size_out):
    rng = np.random.default_rng(0)
    img = rng.random((size_in[1], size_in[0], 3)).astype(np.float32)
    got = downsample_area(img, *size_out)
    assert got.shape == (size_out[1], size_out[0], 3) and got.dtype == np.float32
    # float32 sums of at most a few dozen terms in [0, 1]: 1e-5 covers the rounding.
    np.testing.assert_allclose(got, _box_reference(img, *size_out), atol=1e-5)


def test_coarse_size_rounds_half_up_and_keeps_one_pixel():
    assert coarse_size_wh(504, 378, 0.5) == (252, 189)
    assert coarse_size_wh(5, 3, 0.5) == (3, 2)  # 2.5 -> 3, 1.5 -> 2
    assert coarse_size_wh(10, 10, 0.01) == (1, 1)


def _smooth_model(n: int = 40, seed: int = 1) -> GaussianModel:
    """Opaque-ish Gaussians 0.3-0.5 units wide, 3 units from the camera (>= 2.8 px sigma at the coarse
    size used below), SH degree 0."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.5, 0.5])
    return GaussianModel(means, torch.randn(n, 4, generator=g), torch.log(0.3 + 0.2 * torch.rand(n, 3, generator=g)),
                         torch.full((n,), 1.0), (torch.rand(n, 1, 3, generator=g) - 0.5) * 2, torch.zeros(n, 0, 3))


@pytest.mark.parametrize(("size_wh", "tol"), [((32, 24), 0.01), ((21, 16), 0.02)])
def test_scaled_intrinsics_render_the_downsampled_image(size_wh, tol):
    """A render at W' x H' with `Camera.scaled` intrinsics = the full-size render area-averaged to W' x H'.

    The screen-space low-pass (eps2d, a fixed px^2 blur per resolution) is off so that the only difference
    is point sampling at pixel centres against averaging over the pixel: per axis h^2/24 * |f''|, with
    |f''| <= A / sigma^2 for a Gaussian of amplitude A <= 0.73 (opacity) and sigma >= 2.8 px at 32x24
    (>= 1.85 px at 21x16), i.e. <= 0.008 (0.018) for both axes. The intrinsics of the pixel-centre
    convention (cx' = (cx - 0.5) s + 0.5), off by a quarter pixel here, must fail that tolerance.
    """
    W, H = 64, 48
    model = _smooth_model()
    cam = Camera.pinhole(60.0, 57.0, 0.52 * W, 0.47 * H, W, H)
    pose = look_at_cam_from_world([0.2, 0.1, -3.0], [0.0, 0.0, 0.0]).numpy()[None]
    cfg = RasterConfig(eps2d=0.0)
    w, h = size_wh
    reference = downsample_area(render_views(model, [cam], pose, config=cfg)[0], w, h)
    got = render_views(model, [cam.scaled(w, h)], pose, config=cfg)[0]
    assert np.abs(got - reference).max() < tol
    sx, sy = w / W, h / H
    centre_conv = Camera.pinhole(cam.fx * sx, cam.fy * sy, (cam.cx - 0.5) * sx + 0.5, (cam.cy - 0.5) * sy + 0.5, w, h)
    wrong = render_views(model, [centre_conv], pose, config=cfg)[0]
    assert np.abs(wrong - reference).max() > 2 * tol


def test_densify_statistics_are_resolution_free():
    """`accumulate` given the rendered size yields the same statistics at half size as at full size
    (pixel gradients x2, half-side /2); the loop passes the rendered size. Equal up to the sampling
    difference of the two renders (~10% here); a wrong size would make them differ by a factor 2."""
    W, H = 96, 72
    gt = _smooth_model(seed=5)
    cam = Camera.pinhole(90.0, 85.0, 0.52 * W, 0.47 * H, W, H)
    pose = look_at_cam_from_world([0.2, 0.1, -3.0], [0.0, 0.0, 0.0])
    target = render_views(gt, [cam], pose.numpy()[None])[0]
    g = torch.Generator().manual_seed(9)
    model = GaussianModel(gt.means.detach() + 0.05 * torch.randn(gt.means.shape, generator=g),
                          gt.quats.detach(), gt.log_scales.detach(), gt.opacity_logits.detach(), gt.sh0.detach(),
                          gt.shN.detach())
    sums = {}
    for s in (1.0, 0.5):
        w, h = coarse_size_wh(W, H, s)
        out = model.render(pose.float(), pinhole_K(cam.scaled(w, h)), w, h, sh_degree=0)
        out.projected.means2d.retain_grad()
        t = torch.as_tensor(downsample_area(target, w, h)).permute(2, 0, 1)
        photometric_loss(out.rgb, t).backward()
        state = DensifyState.zeros(model.num_gaussians, "cpu")
        accumulate(state, out.projected.means2d.grad, out.projected.visible, w, h)
        sums[s] = float(state.grad_accum.sum())
        for p in model.params_dict().values():
            p.grad = None
    assert sums[1.0] > 0
    assert 0.8 < sums[0.5] / sums[1.0] < 1.25


@pytest.mark.parametrize(("field", "value"), [("coarse_scale", 0.0), ("coarse_scale", 1.5),
                                              ("coarse_scale", math.nan), ("coarse_fraction", -0.1),
                                              ("coarse_fraction", 1.01), ("coarse_fraction", math.inf)])
def test_bad_schedule_values_name_the_field(field, value, tiny):
    cfg = TrainConfig(iters=2, **{field: value})
    with pytest.raises(ConfigError, match=field) as info:
        train_gaussians(*tiny["args"], cfg)
    assert info.value.key == field


@pytest.fixture(scope="module")
def tiny():
    W, H = 40, 30
    gt = _smooth_model(n=60, seed=3)
    cam = Camera.pinhole(40.0, 40.0, W / 2, H / 2, W, H)
    poses = np.stack([look_at_cam_from_world([x, 0.1 * x, -3.0], [0.0, 0.0, 0.0]).numpy()[:3]
                      for x in (-0.5, -0.15, 0.2, 0.5)])
    images = render_views(gt, [cam] * len(poses), poses)
    rng = np.random.default_rng(4)
    xyz = gt.means.detach().numpy().astype(np.float64) + rng.normal(scale=0.05, size=(gt.num_gaussians, 3))
    rgb = np.full((gt.num_gaussians, 3), 128, np.uint8)
    return {"args": (images, [cam] * len(poses), poses, xyz, rgb), "size_wh": (W, H)}


def test_coarse_schedule_trains_at_both_sizes_and_reports_substeps(tiny, monkeypatch):
    images, cams, poses, xyz, rgb = tiny["args"]
    W, H = tiny["size_wh"]
    seen: list[tuple[int, int]] = []
    densify_sizes: list[tuple[int, int]] = []
    real_loss, real_accumulate = train_mod.photometric_loss, train_mod.accumulate

    def loss_spy(rendered, target, **kw):
        assert rendered.shape == target.shape
        seen.append((rendered.shape[2], rendered.shape[1]))
        return real_loss(rendered, target, **kw)

    def accumulate_spy(state, grad, visible, width, height):
        densify_sizes.append((width, height))
        return real_accumulate(state, grad, visible, width, height)

    render_K: dict[tuple[int, int], torch.Tensor] = {}
    render_eps2d: dict[tuple[int, int], set[float]] = {}
    real_render = GaussianModel.render

    def render_spy(self, cam_from_world, K, width, height, **kw):
        render_K.setdefault((width, height), K.clone())
        render_eps2d.setdefault((width, height), set()).add(kw["config"].eps2d)
        return real_render(self, cam_from_world, K, width, height, **kw)

    monkeypatch.setattr(train_mod, "photometric_loss", loss_spy)
    monkeypatch.setattr(GaussianModel, "render", render_spy)
    monkeypatch.setattr(train_mod, "accumulate", accumulate_spy)
    cfg = TrainConfig(iters=40, sh_degree=0, optimize_poses=False, coarse_scale=0.5, coarse_fraction=0.6,
                      densify=DensifyConfig(start_iter=10, stop_iter=30, every=10), log_every=5,
                      coarse_raster=RasterConfig(eps2d=0.2))
    res = train_gaussians(images, cams, poses, xyz, rgb, cfg)
    coarse = coarse_size_wh(W, H, 0.5)
    assert seen == [coarse] * 24 + [(W, H)] * 16
    assert densify_sizes == [coarse] * 24 + [(W, H)] * 6
    torch.testing.assert_close(render_K[coarse], pinhole_K(cams[0].scaled(*coarse)))
    torch.testing.assert_close(render_K[(W, H)], pinhole_K(cams[0]))
    assert render_eps2d == {coarse: {0.2}, (W, H): {RasterConfig().eps2d}}
    monkeypatch.undo()

    before = GaussianModel.from_points(xyz, rgb, sh_degree=0)
    err0 = np.mean([np.mean((a - b) ** 2) for a, b in zip(render_views(before, cams, poses), images, strict=True)])
    err1 = np.mean([np.mean((a - b) ** 2) for a, b in zip(render_views(res.model, cams, poses), images, strict=True)])
    assert err1 < 0.5 * err0

    t = res.timings_s
    assert {"setup", "optimize", "total"} <= set(t)
    parts = [t[f"optimize/{k}"] for k in OPTIMIZE_SUBSTEPS]
    assert all(p >= 0 for p in parts) and t["optimize/render"] > 0 and t["optimize/densify"] > 0
    assert t["optimize/callback"] == 0.0
    # The laps tile the loop: their sum is "optimize" less the progress bar's setup (rounding 1e-4 each).
    # The lower bound is loose: a preemption between two laps on a loaded machine counts in no lap.
    assert sum(parts) <= t["optimize"] + 1e-3
    assert sum(parts) > 0.5 * t["optimize"]
    assert t["total"] == pytest.approx(t["setup"] + t["optimize"], abs=2e-4)


def test_schedule_off_matches_the_plain_loop(tiny):
    """coarse_fraction 0 or coarse_scale 1 is the full-size loop, bit for bit (same seed)."""
    images, cams, poses, xyz, rgb = tiny["args"]
    base = TrainConfig(iters=12, sh_degree=0, optimize_poses=False)
    ref = train_gaussians(images, cams, poses, xyz, rgb, base)
    for cfg in (TrainConfig(iters=12, sh_degree=0, optimize_poses=False, coarse_scale=0.5, coarse_fraction=0.0),
                TrainConfig(iters=12, sh_degree=0, optimize_poses=False, coarse_scale=1.0, coarse_fraction=0.7)):
        res = train_gaussians(images, cams, poses, xyz, rgb, cfg)
        torch.testing.assert_close(res.model.means, ref.model.means, rtol=0, atol=0)
        assert res.history.loss == ref.history.loss
