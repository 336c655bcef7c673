"""Global alignment (DUSt3R objective) on pointmaps built from known geometry."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from mvgeo.align.alignment_objective import (
    Adam,
    _build_terms,
    _Grid,
    _Params,
    _sample_mask,
    _term_index,
    alignment_loss,
    alignment_loss_and_grads,
    alignment_loss_reference,
)
from mvgeo.align.global_align import (
    GlobalAlignConfig,
    _spread,
    global_align,
    init_from_spanning_tree,
    pixel_rays,
)
from mvgeo.common.errors import DegenerateGeometryError
from mvgeo.metrics import compare_poses
from mvgeo.transforms import quat_from_R

from .synthetic import make_pairs, make_views

FOCAL = 30.0


def _metrics(est, ref):
    names = [f"{k}" for k in range(len(ref))]
    return compare_poses(dict(zip(names, est, strict=True)), dict(zip(names, ref, strict=True)))


def test_exact_pointmaps_mst_init_recovers_poses(rng):
    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng)
    init = init_from_spanning_tree(preds, [d.shape for d in depths], focal_init_px=np.full(4, FOCAL))
    m = _metrics(init.cam_from_world, poses)
    # Exact pointmaps and the true focal: chaining + PnP are exact up to float64 round-off.
    assert m.median_rotation_deg < 1e-4
    assert m.ate.rmse < 1e-6


def test_optimisation_recovers_focal_and_poses_from_noisy_pointmaps(rng):
    poses, depths = make_views(5)
    preds = make_pairs(poses, depths, FOCAL, rng, noise=0.002, focal_err=0.1)
    sizes = [d.shape for d in depths]
    init = global_align(preds, sizes, config=GlobalAlignConfig(iters=0))
    res = global_align(preds, sizes, config=GlobalAlignConfig(iters=300, lr=0.02))
    m = _metrics(res.cam_from_world, poses)
    m0 = _metrics(init.cam_from_world, poses)
    assert res.final_loss < init.final_loss
    # The optimisation must improve on the MST initialisation (measured 0.088 -> 0.036 deg worst pair).
    assert m.rotation_deg.max() < m0.rotation_deg.max()
    # 0.2 % point noise, 768 px per view, 10 % focal error at init: measured 0.036 deg and <0.6 % focal
    # error after 300 iterations; the bounds leave ~3x margin for platform differences.
    assert m.rotation_deg.max() < 0.1
    assert np.all(np.abs(res.focal_px / FOCAL - 1) < 0.02)
    assert all(np.isfinite(d).all() for d in res.depth)


def test_shared_focal_and_fixed_focal(rng):
    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng, focal_err=0.05)
    res = global_align(preds, [d.shape for d in depths], config=GlobalAlignConfig(iters=50, shared_focal=True))
    assert np.ptp(res.focal_px) == 0.0
    fixed = global_align(preds, [d.shape for d in depths], focal_init_px=np.full(4, FOCAL),
                         config=GlobalAlignConfig(iters=50, optimize_focal=False))
    np.testing.assert_allclose(fixed.focal_px, FOCAL, rtol=1e-6)  # float32 storage of log f


def test_vectorised_loss_matches_loop_reference(rng):
    """The fast loss against the slow per-pixel loop, in float64, at a random (non-optimal) state."""
    poses, depths = make_views(3, H=6, W=8, focal=8.0)
    preds = make_pairs(poses, depths, 8.0, rng, noise=0.01)
    sizes = [d.shape for d in depths]
    n = 3
    cam = poses.copy()
    cam[:, :, 3] += 0.05 * rng.normal(size=(n, 3))
    focal = 8.0 * (1 + 0.1 * rng.random(n))
    dep = [d * (1 + 0.05 * rng.random(d.shape)) for d in depths]
    sims = [(float(np.exp(rng.normal())), np.linalg.qr(rng.normal(size=(3, 3)))[0], rng.normal(size=3))
            for _ in preds]
    sims = [(s, R * np.sign(np.linalg.det(R)), t) for s, R, t in sims]
    ref = alignment_loss_reference(preds, cam_from_world=cam, focal_px=focal, depth=dep, pair_sim=sims,
                                   pinned_scale=1.0)
    dt = torch.float64
    offsets = np.array([0, 48, 96])
    T = lambda x: torch.as_tensor(np.asarray(x), dtype=dt)  # noqa: E731
    R_wfc = np.transpose(cam[:, :, :3], (0, 2, 1))
    t_wfc = -np.einsum("nij,nj->ni", R_wfc, cam[:, :, 3])
    params = _Params(T(np.concatenate([np.log(d).ravel() for d in dep])), T(quat_from_R(R_wfc)), T(t_wfc),
                     T(np.log(focal)), T(quat_from_R(np.stack([R for _, R, _ in sims]))),
                     T(np.stack([t for _, _, t in sims])), T(np.log([s for s, _, _ in sims])), optimize_focal=True)
    terms = _build_terms(preds, sizes, offsets, dt, torch.device("cpu"))
    du = np.concatenate([pixel_rays(6, 8, 1.0)[..., 0].ravel()] * 3)
    dv = np.concatenate([pixel_rays(6, 8, 1.0)[..., 1].ravel()] * 3)
    grid = _Grid(T(du), T(dv), torch.arange(3).repeat_interleave(48), [0, 48, 96, 144])
    fast = float(alignment_loss(params, terms, grid, pinned_scale=1.0).detach())
    # Same float64 arithmetic in a different order: agreement to ~1e-12 relative.
    assert fast == pytest.approx(ref, rel=1e-10)


def test_loss_gradcheck(rng):
    """Analytic (autograd) gradient of the objective vs finite differences, float64."""
    poses, depths = make_views(3, H=4, W=5, focal=5.0)
    preds = make_pairs(poses, depths, 5.0, rng, noise=0.01)
    sizes = [d.shape for d in depths]
    dt = torch.float64
    offsets = np.array([0, 20, 40])
    terms = _build_terms(preds, sizes, offsets, dt, torch.device("cpu"))
    du = torch.as_tensor(np.concatenate([pixel_rays(4, 5, 1.0)[..., 0].ravel()] * 3), dtype=dt)
    dv = torch.as_tensor(np.concatenate([pixel_rays(4, 5, 1.0)[..., 1].ravel()] * 3), dtype=dt)
    grid = _Grid(du, dv, torch.zeros(60, dtype=torch.long), [0, 20, 40, 60])
    g = torch.Generator().manual_seed(0)
    shapes = [(60,), (3, 4), (3, 3), (1,), (len(preds), 4), (len(preds), 3), (len(preds),)]
    inputs = tuple(torch.randn(s, generator=g, dtype=dt, requires_grad=True) * 0.3 for s in shapes)
    inputs = tuple(x.detach().requires_grad_(True) for x in inputs)
    with torch.no_grad():
        inputs[1][:, 0] += 1.0  # keep quaternions away from zero
        inputs[4][:, 0] += 1.0

    names = ["log_depth", "q_wfc", "t_wfc", "log_focal", "q_pair", "t_pair", "logs_pair"]

    def f(*xs):
        # the loss only reads these attributes; plain tensors let gradients flow to the inputs
        p = SimpleNamespace(**dict(zip(names, xs, strict=True)))
        return alignment_loss(p, terms, grid, pinned_scale=1.0)

    # The Euclidean norm is smooth away from zero residuals, which random states avoid.
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("shared_focal, optimize_focal", [(False, True), (True, True), (False, False)])
def test_chain_rule_gradient_matches_autograd(rng, shared_focal, optimize_focal):
    """`alignment_loss_and_grads` (numpy chain rule, the optimiser's path) against autograd of the
    loss, float64, at a random state with unnormalised quaternions and a pixel stride's gaps."""
    poses, depths = make_views(3, H=6, W=8, focal=8.0)
    preds = make_pairs(poses, depths, 8.0, rng, noise=0.01)
    sizes = [d.shape for d in depths]
    dt = torch.float64
    terms = _build_terms(preds, sizes, np.array([0, 48, 96]), dt, torch.device("cpu"), stride=2)
    du = torch.as_tensor(np.concatenate([pixel_rays(6, 8, 1.0)[..., 0].ravel()] * 3), dtype=dt)
    dv = torch.as_tensor(np.concatenate([pixel_rays(6, 8, 1.0)[..., 1].ravel()] * 3), dtype=dt)
    fpix = torch.zeros(144, dtype=torch.long) if shared_focal else torch.arange(3).repeat_interleave(48)
    grid = _Grid(du, dv, fpix, [0, 48, 96, 144])
    g = torch.Generator().manual_seed(1)
    E = len(preds)
    q_wfc, q_pair = torch.randn(3, 4, generator=g, dtype=dt), torch.randn(E, 4, generator=g, dtype=dt)
    q_wfc[:, 0] += 2.0
    log_depth = torch.randn(144, generator=g, dtype=dt) * 0.3 + 1.0
    params = _Params(log_depth, q_wfc, torch.randn(3, 3, generator=g, dtype=dt),
                     torch.log(torch.full((1 if shared_focal else 3,), 8.0, dtype=dt)), q_pair,
                     torch.randn(E, 3, generator=g, dtype=dt), torch.randn(E, generator=g, dtype=dt) * 0.3,
                     optimize_focal=optimize_focal)
    loss = alignment_loss(params, terms, grid, pinned_scale=1.5)
    loss.backward()
    value, grads = alignment_loss_and_grads(params, _term_index(terms, grid), pinned_scale=1.5)
    assert value == pytest.approx(float(loss.detach()), rel=1e-12)
    named = {k: p for k, p in params.named_parameters() if p.requires_grad}
    assert set(grads) == set(named)
    for k, p in named.items():
        np.testing.assert_allclose(grads[k].reshape(p.shape), p.grad.numpy(), rtol=1e-9, atol=1e-12, err_msg=k)


def test_disconnected_views_raise(rng):
    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng, pairs=[(0, 1), (2, 3)])
    with pytest.raises(DegenerateGeometryError, match="disconnected"):
        global_align(preds, [d.shape for d in depths], config=GlobalAlignConfig(iters=0))


def test_own_adam_matches_torch_optim(rng):
    """`Adam` against `torch.optim.Adam` on a quadratic: identical iterates (float64)."""

    target = torch.as_tensor(rng.normal(size=5))
    a = torch.zeros(5, dtype=torch.float64, requires_grad=True)
    b = torch.zeros(5, dtype=torch.float64, requires_grad=True)
    ours = Adam([a], betas=(0.9, 0.9))
    ref = torch.optim.Adam([b], lr=0.1, betas=(0.9, 0.9))
    for k in range(20):
        lr = 0.1 / (1 + k)
        for g in ref.param_groups:
            g["lr"] = lr
        a.grad = None
        ((a - target) ** 4).sum().backward()
        ours.step(lr)
        ref.zero_grad()
        ((b - target) ** 4).sum().backward()
        ref.step()
    # Same formula, possibly different operation order: agreement to float64 round-off.
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_pixel_stride_recovers_poses_and_fills_all_depths(rng):
    """Strided alignment (every 2nd pixel) against the same problem on all pixels."""
    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng, noise=0.002, focal_err=0.05)
    sizes = [d.shape for d in depths]
    full = global_align(preds, sizes, config=GlobalAlignConfig(iters=150, lr=0.02))
    strided = global_align(preds, sizes, config=GlobalAlignConfig(iters=150, lr=0.02, pixel_stride=2))
    m_full, m_str = _metrics(full.cam_from_world, poses), _metrics(strided.cam_from_world, poses)
    # A quarter of the pixels still constrain 4 poses tightly: within 2x of the full problem's error
    # (measured: both ~0.02 deg) and under the full-problem bound of the test above.
    assert m_str.rotation_deg.max() < max(2 * m_full.rotation_deg.max(), 0.02)
    assert m_str.rotation_deg.max() < 0.1
    for d_full, d_str in zip(full.depth, strided.depth, strict=True):
        assert d_str.shape == d_full.shape and np.isfinite(d_str).all()
        # Unsampled pixels get their sampled neighbours' correction: depths agree to a few percent.
        assert np.median(np.abs(d_str / d_full - 1)) < 0.03


@pytest.mark.parametrize("stride", [2, 3, 4, 8])
def test_spread_interpolates_the_sampled_corrections_bilinearly(stride):
    """`_spread` against its definition: a correction linear in the pixel coordinates, given at the samples
    only, comes back exactly between the outermost samples (bilinear interpolation of a linear function)
    and, beyond them, as its value at the clamped coordinate (the outermost sample's). Two views of
    different sizes, so the second's offset is exercised."""
    sizes = [(37, 45), (29, 21)]
    coeffs = [(0.3, -0.02, 0.01), (-0.1, 0.004, 0.03)]
    offsets = np.concatenate([[0], np.cumsum([h * w for h, w in sizes])[:-1]])
    delta = np.zeros(sum(h * w for h, w in sizes))
    for (H, W), o, (a, b, c) in zip(sizes, offsets, coeffs, strict=True):
        y, x = np.mgrid[0:H, 0:W].astype(float)
        mask = _sample_mask(H, W, stride).reshape(H, W)
        delta[o:o + H * W] = np.where(mask, a + b * x + c * y, np.nan).reshape(-1)  # only samples are read
    out = _spread(delta, sizes, offsets, stride)
    for (H, W), o, (a, b, c) in zip(sizes, offsets, coeffs, strict=True):
        ys, xs = np.arange(stride // 2, H, stride), np.arange(stride // 2, W, stride)
        yc = np.clip(np.arange(H), ys[0], ys[-1])[:, None]
        xc = np.clip(np.arange(W), xs[0], xs[-1])[None, :]
        np.testing.assert_allclose(out[o:o + H * W].reshape(H, W), a + b * xc + c * yc, rtol=0, atol=1e-12)


def test_pair_similarities_fall_back_to_every_pixel_where_the_samples_hold_too_few(rng):
    """The start's pair similarities are fitted on the alignment's samples; a pair with no confident point
    on them (here: pair 0's confidence lowered to 1 on every sampled pixel) is fitted on all its pixels,
    where the strided fit alone would be degenerate."""
    from dataclasses import replace as dc_replace

    from mvgeo.align.pointmap_geometry import pair_similarities, weighted_umeyama

    poses, depths = make_views(4)
    preds = make_pairs(poses, depths, FOCAL, rng, noise=0.002, focal_err=0.05)
    sizes = [d.shape for d in depths]
    init = init_from_spanning_tree(preds, sizes, focal_init_px=np.full(4, FOCAL))
    k = 8
    p0 = preds[0]
    ci, cj = p0.conf_i.copy(), p0.conf_j.copy()
    ci[k // 2::k, k // 2::k] = 1.0
    cj[k // 2::k, k // 2::k] = 1.0
    preds = [dc_replace(p0, conf_i=ci, conf_j=cj), *preds[1:]]
    args = (preds, sizes, init.cam_from_world, init.depth, init.focal_px)
    strided, full = pair_similarities(*args, pixel_stride=k), pair_similarities(*args)
    s0, R0, t0 = strided[0]
    assert s0 == full[0][0] and np.array_equal(R0, full[0][1]) and np.array_equal(t0, full[0][2])
    # The other pairs keep their fit on the samples (fewer points: not the full fit's numbers).
    assert all(a[0] != b[0] for a, b in zip(strided[1:], full[1:], strict=True))
    # On its samples alone pair 0 has no confident point: the fit the fallback replaces is degenerate.
    with pytest.raises(DegenerateGeometryError):
        weighted_umeyama(np.zeros((0, 3)), np.zeros((0, 3)), np.log(np.concatenate(
            [c[k // 2::k, k // 2::k][c[k // 2::k, k // 2::k] > 1.0] for c in (ci, cj)])))
