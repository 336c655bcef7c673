"""`render_views` gives the same images whatever torch's thread count outside it (`RENDER_TORCH_THREADS`)."""

from __future__ import annotations

import numpy as np
import torch

from mvgeo.camera import Camera
from splat import render
from splat.gaussian_model import GaussianModel
from tests.splat.scenes import random_scene

N = 100000


def _with_threads(n: int, fn):
    saved = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        out = fn()
        assert torch.get_num_threads() == n  # the caller's count is restored
        return out
    finally:
        torch.set_num_threads(saved)


def _odd_threads(logits: torch.Tensor) -> tuple[int, torch.Tensor]:
    """The smallest thread count (2..8) at which torch's vectorised sigmoid differs from one thread in the last
    bit of some elements (elements at the threads' chunk ends take another code path), and those elements.
    Which count does it depends on the CPU's vector width: 3 on an AVX-512 Intel Xeon, 4 on an AVX2 AMD EPYC
    (the locked torch, uv.lock)."""
    a = _with_threads(1, lambda: torch.sigmoid(logits))
    for t in range(2, 9):
        odd = (_with_threads(t, lambda t=t: torch.sigmoid(logits)) != a).nonzero().flatten()
        if len(odd):
            return t, odd
    # The test's premise, a property of the locked torch: if a torch computes the sigmoid alike for every
    # thread count, find the op that still differs and build the scene around it instead.
    raise AssertionError("torch's sigmoid no longer depends on the thread count: this scene tests nothing")


def _scene() -> tuple[GaussianModel, int]:
    """Random Gaussians; the ones whose opacity (torch's sigmoid) differs in its last bit between 1 thread and
    `_odd_threads`' count are moved in front of the others, into the middle of the view, so that the
    difference reaches the pixels. Returns the scene and that count."""
    p = random_scene(N, seed=0, dtype=torch.float32, sh_degree=1)
    logits = torch.randn(N, generator=torch.Generator().manual_seed(0)) * 3
    threads, odd = _odd_threads(logits)
    means, log_scales = p["means"].clone(), p["log_scales"].clone()
    means[odd] = torch.tensor([0.0, 0.0, -1.5])  # the camera is at z = -3, looking along +z
    log_scales[odd] = float(np.log(0.2))
    sh = p["sh"]
    return GaussianModel(means, p["quats"], log_scales, logits, sh[:, :1], sh[:, 1:]), threads


def _render(model: GaussianModel, outer: int) -> list[np.ndarray]:
    cam = Camera.pinhole(width=128, height=96, fx=110.0, fy=110.0, cx=64.0, cy=48.0)
    pose = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 3.0]])
    return _with_threads(outer, lambda: render.render_views(model, [cam], pose[None]))


def test_render_is_independent_of_the_callers_threads(monkeypatch):
    model, threads = _scene()
    a, b = _render(model, 1), _render(model, threads)
    assert np.array_equal(a[0], b[0])
    assert a[0].std() > 0.01  # the scene is in view
    # The control: left to the caller's count, the pixels differ (why the count is fixed).
    monkeypatch.setattr(render, "RENDER_TORCH_THREADS", None)
    assert not np.array_equal(_render(model, 1)[0], _render(model, threads)[0])
