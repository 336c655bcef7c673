"""Adaptive density control (clone / split / prune) and its bookkeeping of optimizer state."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splat.densify import DensifyConfig, DensifyState, accumulate, densify_and_prune
from splat.gaussian_model import PARAM_NAMES, GaussianModel
from splat.train import TrainConfig, train_gaussians
from tests.splat.test_train import scene  # noqa: F401  (module fixture: a small self-rendered scene)

EXTENT = 1.0
CFG = DensifyConfig(grad_threshold=1e-3, percent_dense=0.1, prune_opacity=0.05)


def _model():
    """8 Gaussians with hand-picked roles (index: role):
    0 big gradient, small -> cloned;   1 big gradient, large -> split;
    2 small gradient, small -> kept;   3 small gradient, large -> kept;
    4 opacity 0.01 -> pruned;          5 big gradient, small, opacity 0.01 -> cloned (and kept);
    6 big gradient, large, opacity 0.01 -> split;  7 never visible -> kept.
    """
    n = 8
    g = torch.Generator().manual_seed(0)
    small, large = math.log(0.05), math.log(0.5)  # vs percent_dense * extent = 0.1
    log_scales = torch.tensor([small, large, small, large, small, small, large, small])[:, None].repeat(1, 3)
    log_scales[:, 1] -= 0.3  # anisotropic: the largest axis decides
    opac = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.01, 0.01, 0.01, 0.5])
    model = GaussianModel(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g), log_scales,
                          torch.logit(opac), torch.randn(n, 1, 3, generator=g), torch.randn(n, 3, 3, generator=g))
    state = DensifyState.zeros(n, "cpu")
    grads = torch.zeros(n, 2)
    grads[[0, 1, 5, 6], 0] = 3e-3 / (0.5 * 100)  # above threshold after the 0.5 * max(W, H) scaling
    grads[[2, 3, 4], 1] = 0.5e-3 / (0.5 * 100)
    visible = torch.ones(n, dtype=torch.bool)
    visible[7] = False
    grads[7] = 1.0  # ignored: not visible
    for _ in range(2):  # the average over views is what counts
        accumulate(state, grads, visible, 100, 60)
    return model, state


def _optimizer(model):
    groups = [{"params": [getattr(model, k)], "lr": 1e-2, "name": k} for k in PARAM_NAMES]
    deltas = torch.zeros(3, 6, requires_grad=True)
    groups.append({"params": [deltas], "lr": 1e-3, "name": "pose"})
    opt = torch.optim.Adam(groups, eps=1e-15)
    g = torch.Generator().manual_seed(1)
    for p in [*model.parameters(), deltas]:
        p.grad = torch.randn(p.shape, generator=g)
    opt.step()  # non-zero moments to follow
    return opt, deltas


def test_accumulate_averages_visible_views_only():
    _, state = _model()
    np.testing.assert_allclose(state.count.numpy(), [2, 2, 2, 2, 2, 2, 2, 0])
    avg = state.grad_accum / state.count.clamp(min=1)
    np.testing.assert_allclose(avg[[0, 1, 5, 6]].numpy(), 3e-3, rtol=1e-5)
    np.testing.assert_allclose(avg[[2, 3, 4]].numpy(), 0.5e-3, rtol=1e-5)
    assert avg[7] == 0


def test_clone_split_prune_which_and_how_many():
    model, state = _model()
    opt, _ = _optimizer(model)
    old = {k: v.detach().clone() for k, v in model.params_dict().items()}
    new, new_state = densify_and_prune(model, opt, state, CFG, EXTENT, torch.Generator().manual_seed(2))
    # Kept in order: 0, 2, 3, 5, 7 (1 and 6 split, 4 pruned); then clones of 0, 5; then two children each of 1, 6.
    src = [0, 2, 3, 5, 7, 0, 5, 1, 6, 1, 6]
    assert new.num_gaussians == len(src) == 8 - 1 - 2 + 2 + 4
    for k in ("quats", "opacity_logits", "sh0", "shN"):
        torch.testing.assert_close(getattr(new, k).detach(), old[k][src], rtol=0, atol=0)
    torch.testing.assert_close(new.means.detach()[:7], old["means"][src[:7]], rtol=0, atol=0)
    torch.testing.assert_close(new.log_scales.detach()[:7], old["log_scales"][src[:7]], rtol=0, atol=0)
    # Split children: scales / 1.6, means sampled around the parent (within 5 sigma of its largest axis),
    # the two children of one parent differ.
    torch.testing.assert_close(new.log_scales.detach()[7:], old["log_scales"][src[7:]] - math.log(1.6))
    offset = (new.means.detach()[7:] - old["means"][src[7:]]).norm(dim=-1)
    assert (offset > 0).all() and (offset < 5 * 0.5).all()
    assert not torch.equal(new.means[7], new.means[9])
    assert new_state.grad_accum.shape == (11,) and (new_state.count == 0).all()


def test_optimizer_state_follows_the_gaussians():
    model, state = _model()
    opt, deltas = _optimizer(model)
    old_state = {k: {s: opt.state[getattr(model, k)][s].clone() for s in ("exp_avg", "exp_avg_sq")}
                 for k in PARAM_NAMES}
    pose_state = {s: opt.state[deltas][s].clone() for s in ("exp_avg", "exp_avg_sq")}
    new, _ = densify_and_prune(model, opt, state, CFG, EXTENT, torch.Generator().manual_seed(2))
    src_kept = [0, 2, 3, 5, 7]
    for group in opt.param_groups:
        (p,) = group["params"]
        if group["name"] == "pose":
            assert p is deltas
            for s in pose_state:
                assert torch.equal(opt.state[p][s], pose_state[s])
            continue
        assert p is getattr(new, group["name"])  # the optimizer now trains the new model
        st = opt.state[p]
        for s in ("exp_avg", "exp_avg_sq"):
            assert st[s].shape == p.shape
            assert torch.equal(st[s][:5], old_state[group["name"]][s][src_kept])
            assert (st[s][5:] == 0).all()  # clones and split children start fresh
    assert not any(getattr(model, k) in opt.state for k in PARAM_NAMES)  # no stale entries
    # The next step runs and moves every parameter of the new model.
    before = {k: v.detach().clone() for k, v in new.params_dict().items()}
    for p in new.parameters():
        p.grad = torch.ones_like(p)
    opt.step()
    for k, v in new.params_dict().items():
        assert not torch.equal(v.detach(), before[k]), k


def test_max_gaussians_is_respected():
    model, state = _model()
    opt, _ = _optimizer(model)
    cfg = DensifyConfig(grad_threshold=1e-3, percent_dense=0.1, prune_opacity=0.0, max_gaussians=9)
    new, _ = densify_and_prune(model, opt, state, cfg, EXTENT, torch.Generator().manual_seed(2))
    assert new.num_gaussians <= 9


def test_training_with_densification(scene):  # noqa: F811
    cams = [scene["camera"]] * 4
    densify = DensifyConfig(start_iter=10, stop_iter=50, every=10, grad_threshold=2e-5, percent_dense=0.05)
    cfg = TrainConfig(iters=60, sh_degree=0, optimize_poses=False, densify=densify, log_every=5)
    res = train_gaussians(scene["images"][:4], cams, scene["poses"][:4], scene["xyz"], scene["rgb"], cfg)
    counts = res.history.num_gaussians
    assert counts[0] == len(scene["xyz"]) and max(counts) > counts[0], counts  # densification happened
    for p in res.model.parameters():
        assert torch.isfinite(p).all()
    assert np.isfinite(res.history.loss).all()
    assert np.mean(res.history.loss[-3:]) < 0.7 * np.mean(res.history.loss[:3]), res.history.loss


def test_split_children_are_drawn_from_the_parents_own_gaussian():
    # 3DGS samples a split Gaussian's children from N(mean, R diag(s^2) R^T): the parent's own axes. One
    # anisotropic, turned parent copied 2000 times gives 4000 children whose offsets' covariance must be that
    # matrix; sampling along the world axes (R left out) gives diag(s^2), 60 % off in the largest entries.
    from scipy.spatial.transform import Rotation

    n = 2000
    q_xyzw = Rotation.from_rotvec([0.4, -0.9, 0.6]).as_quat()
    quat = torch.tensor([q_xyzw[3], *q_xyzw[:3]], dtype=torch.float32)  # wxyz
    scales = torch.tensor([0.8, 0.3, 0.1], dtype=torch.float32)
    mean = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float32)
    model = GaussianModel(mean.repeat(n, 1), quat.repeat(n, 1), scales.log().repeat(n, 1),
                          torch.full((n,), 2.0, dtype=torch.float32), torch.zeros(n, 1, 3, dtype=torch.float32),
                          torch.zeros(n, 3, 3, dtype=torch.float32))
    state = DensifyState.zeros(n, "cpu")
    accumulate(state, torch.full((n, 2), 1.0), torch.ones(n, dtype=torch.bool), 100, 60)
    opt, _ = _optimizer(model)
    new, _ = densify_and_prune(model, opt, state, CFG, EXTENT, torch.Generator().manual_seed(0))
    offsets = new.means.detach().numpy() - mean.numpy()
    assert offsets.shape == (2 * n, 3)
    R = Rotation.from_quat(q_xyzw).as_matrix()
    expected = R @ np.diag(scales.numpy() ** 2) @ R.T
    # 4000 samples: an entry's standard error is about sqrt(2 / 4000) = 2 % of the largest variance (0.64).
    np.testing.assert_allclose(np.cov(offsets.T), expected, atol=0.1 * 0.64)
    np.testing.assert_allclose(offsets.mean(axis=0), 0.0, atol=0.05)


def test_learning_rate_decays_log_linearly_from_start_to_end():
    from splat.train import _lr_at

    lr0, lr1, total = 1.6e-4, 1.6e-6, 3000
    for step in (0, 750, 1500, 3000, 4000, -5):
        t = min(max(step / total, 0.0), 1.0)
        assert _lr_at(step, total, lr0, lr1) == pytest.approx(lr0 * (lr1 / lr0) ** t, rel=1e-12)
    assert _lr_at(1500, total, lr0, lr1) == pytest.approx(math.sqrt(lr0 * lr1), rel=1e-12)  # the geometric midpoint
