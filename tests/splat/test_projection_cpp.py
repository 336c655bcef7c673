"""The C++ projection (`csrc/projection.cpp`) against the torch reference `project_gaussians`:
values and gradients (pose and K included) in float64 and float32, float64 gradcheck of the
hand-written backward, and scenes with the edge cases (behind the camera, straddling the near
plane, at and far beyond the image border where the Jacobian is clamped, degenerate scales)."""

from __future__ import annotations

import pytest
import torch

from splat.projection import project_gaussians
from tests.splat.scenes import activated, random_camera, random_scene

pytestmark = pytest.mark.needs_cpp_kernel

W, H = 48, 36
OUTPUTS = ("means2d", "conics", "depths", "opacities")


def _edge_scene(dtype):
    """Random Gaussians plus hand-placed edge cases, pre-activation parameters."""
    params = random_scene(40, seed=7, dtype=dtype, spread=1.2)
    cam, K = random_camera(W, H, seed=8, dtype=dtype)
    R, t = cam[:3, :3], cam[:3, 3]
    # Points given in camera coordinates, mapped to the world: behind, at/straddling the near plane,
    # on the image border, far off-axis on all four sides (Jacobian clamp active), ahead in the centre.
    f = K[0, 0]
    z = 3.0
    u_border = (W - K[0, 2]) / f * z
    cam_pts = torch.tensor([
        [0.0, 0.0, -1.0], [0.1, 0.0, 0.005], [0.0, 0.1, 0.05],
        [u_border, 0.0, z], [0.0, (H - K[1, 2]) / K[1, 1] * z, z],
        [4.0 * z, 0.0, z], [-4.0 * z, 0.3, z], [0.2, 4.0 * z, z], [0.1, -4.0 * z, z],
        [0.05, 0.02, z], [0.0, -0.03, z], [0.02, 0.0, z],
    ], dtype=dtype)
    world = (cam_pts - t) @ R  # R^T (p - t)
    k = world.shape[0]
    g = torch.Generator().manual_seed(9)
    log_scales = torch.log(0.05 + 0.1 * torch.rand(k, 3, generator=g, dtype=dtype))
    log_scales[-3, 0] = -18.0  # one degenerate axis (a needle / a disc)
    log_scales[-2, :2] = -18.0
    log_scales[-1, :] = -18.0  # degenerate in every axis: only the eps2d low-pass is left
    params["means"] = torch.cat([params["means"], world])
    params["quats"] = torch.cat([params["quats"], torch.randn(k, 4, generator=g, dtype=dtype)])
    params["log_scales"] = torch.cat([params["log_scales"], log_scales])
    params["opacity_logits"] = torch.cat([params["opacity_logits"], torch.full((k,), 1.0, dtype=dtype)])
    return params, cam, K


def _run(backend, inputs, weights, **kw):
    leaves = [t.detach().clone().requires_grad_(True) for t in inputs]
    p = project_gaussians(*leaves, W, H, backend=backend, **kw)
    outs = [getattr(p, name) for name in OUTPUTS]
    loss = sum((o * w).sum() for o, w in zip(outs, weights, strict=True))
    loss.backward()
    return p, [leaf.grad for leaf in leaves]


def _weights(n, dtype):
    g = torch.Generator().manual_seed(3)
    return [torch.randn(shape, generator=g, dtype=dtype) for shape in ((n, 2), (n, 3), (n,), (n,))]


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("pose_rows", [3, 4])
def test_float64_values_and_gradients_match_torch(antialiased, pose_rows):
    params, cam, K = _edge_scene(torch.float64)
    means, quats, scales, opac, _ = activated(params)
    inputs = [means, quats, scales, opac, cam[:pose_rows], K]
    weights = _weights(means.shape[0], torch.float64)
    ref, g_ref = _run("torch", inputs, weights, antialiased=antialiased)
    got, g_got = _run("cpp", inputs, weights, antialiased=antialiased)
    assert torch.equal(ref.visible, got.visible)
    assert not got.visible[-12].item() and not got.visible[-11].item()  # behind / before the near plane
    if not antialiased:
        assert got.visible[-3:].all()  # degenerate scales are still drawn (the eps2d low-pass)
    else:
        assert not got.visible[-2:].any()  # ... but a flat 2D covariance takes the compensated opacity to ~0
    # Same float64 expressions, evaluated in another order: agreement to rounding (observed ~1e-13 relative).
    for name in (*OUTPUTS, "extents_px"):
        a, b = getattr(ref, name).detach(), getattr(got, name).detach()
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-9 * float(a.abs().max()), msg=name)
    # With antialiasing the last three Gaussians (degenerate scales ~1e-8) are scaled by the compensation
    # sqrt(det / det_aa), whose det = a c - b^2 of a flat 2D covariance is pure cancellation: its derivative
    # amplifies the rounding of that difference, which depends on the evaluation order and the CPU's vector
    # code. Their scale and opacity gradients agree to ~1e-3 relative (1.2e-3 measured on an Intel Xeon; the
    # gradcheck below leaves them out); every other gradient to ~1e-11.
    n = means.shape[0]
    regular = torch.arange(n - 3 if antialiased else n)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "cam_from_world", "K"), g_ref, g_got, strict=True):
        assert b.shape == a.shape, name
        per_gaussian = a.shape[0] == n and name not in ("cam_from_world", "K")
        a_reg, b_reg = (a[regular], b[regular]) if per_gaussian else (a, b)
        torch.testing.assert_close(b_reg, a_reg, rtol=1e-8, atol=1e-9 * float(a.abs().max()), msg=name)
        if per_gaussian and antialiased:
            torch.testing.assert_close(b[n - 3:], a[n - 3:], rtol=1e-2, atol=1e-9 * float(a.abs().max()),
                                       msg=f"{name}, degenerate scales")


def test_float32_values_and_gradients_match_torch():
    params, cam, K = _edge_scene(torch.float64)
    means, quats, scales, opac, _ = activated({k: v.float() for k, v in params.items()})
    inputs = [means, quats, scales, opac, cam.float(), K.float()]
    weights = _weights(means.shape[0], torch.float32)
    ref, g_ref = _run("torch", inputs, weights)
    got, g_got = _run("cpp", inputs, weights)
    assert got.means2d.dtype == torch.float32 and got.conics.dtype == torch.float32
    assert torch.equal(ref.visible, got.visible)
    vis = ref.visible
    # The kernel computes in float64 and rounds once; the reference rounds after every float32 op. The
    # 2D covariance goes through det = a c - b^2, whose cancellation amplifies float32 rounding by
    # ~cond(Sigma2d) (up to ~1e3 for the needle-like Gaussians): 1e-3 relative to each output's scale
    # is that bound with a margin (observed ~1e-5).
    for name in OUTPUTS:
        a, b = getattr(ref, name).detach()[vis], getattr(got, name).detach()[vis]
        torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-4 * float(a.abs().max()), msg=name)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "cam_from_world", "K"), g_ref, g_got, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-3 * float(a.abs().max()), msg=name)


@pytest.mark.parametrize("antialiased", [False, True])
def test_cpp_backward_gradcheck(antialiased):
    # Includes the four far off-axis Gaussians whose Jacobian is evaluated at the clamped point, where the
    # pose and K enter through the clamp limits; no input sits on a kink (clamp edge, near plane).
    params, cam, K = _edge_scene(torch.float64)
    means, quats, scales, opac, _ = activated(params)
    # With antialiasing the degenerate-scale Gaussians sit at sqrt(det ~ 0), not differentiable: left out.
    last = means.shape[0] - (3 if antialiased else 0)
    keep = torch.cat([torch.arange(8), torch.arange(means.shape[0] - 9, last)])
    inputs = [t[keep].clone().requires_grad_(True) for t in (means, quats, scales, opac)]
    inputs += [cam.clone().requires_grad_(True), K.clone().requires_grad_(True)]

    def fn(*args):
        p = project_gaussians(*args, W, H, antialiased=antialiased, backend="cpp")
        return p.means2d, p.conics, p.depths, p.opacities

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_clamped_jacobian_is_exercised():
    """The off-axis Gaussians of the edge scene do hit the Jacobian clamp (else gradcheck would not test it)."""
    params, cam, K = _edge_scene(torch.float64)
    means = params["means"][-7:-3]
    p_cam = means @ cam[:3, :3].T + cam[:3, 3]
    ratio_x = (p_cam[:, 0] / p_cam[:, 2]).abs()
    ratio_y = (p_cam[:, 1] / p_cam[:, 2]).abs()
    limit = (W + 0.3 * 0.5 * W) / K[0, 0]
    assert ((ratio_x > limit) | (ratio_y > limit)).all()


def test_threads_do_not_change_the_result():
    params = random_scene(20_000, seed=5, dtype=torch.float32, spread=1.0)
    cam, K = random_camera(W, H, seed=6, dtype=torch.float32)
    means, quats, scales, opac, _ = activated(params)
    one = project_gaussians(means, quats, scales, opac, cam, K, W, H, backend="cpp", num_threads=1)
    two = project_gaussians(means, quats, scales, opac, cam, K, W, H, backend="cpp", num_threads=3)
    for name in (*OUTPUTS, "extents_px", "visible"):
        assert torch.equal(getattr(one, name), getattr(two, name)), name


def test_unknown_backend_is_refused():
    params = random_scene(3, seed=1)
    cam, K = random_camera(W, H, seed=1)
    means, quats, scales, opac, _ = activated(params)
    with pytest.raises(ValueError, match="unknown splat backend"):
        project_gaussians(means, quats, scales, opac, cam, K, W, H, backend="cuda")
