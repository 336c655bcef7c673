"""The denoiser's thread-count-independent parallelism (`denoise.parallel`, `denoise.n2v.chunked_backward`)."""

import threading

import numpy as np
import pytest
import torch

from denoise.inference import denoise_images, mean_of_passes, predict_tiled, tile_starts
from denoise.model import N2VModel
from denoise.n2v import (
    N2VConfig,
    StepBatch,
    chunk_bounds,
    chunked_backward,
    masked_mse,
    new_model,
    optimise_unet,
    train_n2v,
    weight_sharing_replicas,
)
from denoise.parallel import IN_FLIGHT_BYTES, budget, group_size, one_thread_per_task, run_tasks
from denoise.round2 import Round2Config, jinvariant_predict
from denoise.self_supervised import denoise_with_method, train_self_supervised
from denoise.unet import UNet, UNetConfig
from mvgeo.common.errors import ConfigError
from tests.denoise._reference import reference_training
from tests.denoise._synth import add_noise, smooth_scene


@pytest.fixture
def outer_threads():
    """Set the caller's torch thread count for a block; restored after the test."""
    saved = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(saved)


def _net(width: int = 8):
    cfg = N2VConfig(unet=UNetConfig(width=width, depth=2))
    return new_model(cfg, [torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(0))], seed=0).unet


def test_chunk_bounds_cover_the_batch_in_order():
    for n in range(1, 12):
        for k in range(1, 5):
            b = chunk_bounds(n, k)
            assert len(b) == min(n, k)
            assert b[0][0] == 0 and b[-1][1] == n
            assert all(b1 == a2 for (_, b1), (a2, _) in zip(b[:-1], b[1:], strict=True))
            sizes = [stop - start for start, stop in b]
            assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)


def test_chunked_gradient_matches_the_whole_batch(outer_threads):
    """Reference: the whole batch's loss backpropagated through one network. A mean loss split into chunks
    weighted by their share gives the same gradient up to float32 round-off (the sums are reordered: 1e-6
    relative); a masked mean is averaged per chunk instead, so it is compared with that definition."""
    outer_threads(1)
    net = _net()
    g = torch.Generator().manual_seed(3)
    x = torch.randn(5, 3, 32, 32, generator=g)
    target = torch.randn(5, 3, 32, 32, generator=g)
    mask = torch.rand(5, 1, 32, 32, generator=g) < 0.1

    def mse(unet, x, target, mask):
        return torch.mean((unet(x) - target) ** 2)

    def masked(unet, x, target, mask):
        return masked_mse(unet(x), target, mask)

    def grads(module):
        return torch.cat([p.grad.flatten() for p in module.parameters()])

    for loss in (mse, masked):
        net.zero_grad()
        if loss is mse:
            loss(net, x, target, mask).backward()
        else:  # per-chunk masked means of the chunks 0:3 and 3:5, weighted 3/5 and 2/5
            (loss(net, x[:3], target[:3], mask[:3]) * 0.6 + loss(net, x[3:], target[3:], mask[3:]) * 0.4).backward()
        reference = grads(net).clone()
        replicas = weight_sharing_replicas(net, 2, batch_size=5)
        value = chunked_backward(replicas, StepBatch((x, target, mask), loss))
        got = grads(net)
        assert np.isfinite(value)
        torch.testing.assert_close(got, reference, rtol=1e-5, atol=1e-7)
        assert replicas[1].parameters().__next__().data_ptr() == net.parameters().__next__().data_ptr()


def test_chunks_give_the_same_bits_on_one_thread_or_several(outer_threads):
    net = _net(16)
    x = torch.randn(8, 3, 48, 48, generator=torch.Generator().manual_seed(4))

    def loss(unet, x):
        return unet(x).square().mean()

    def run(threads: int) -> torch.Tensor:
        outer_threads(threads)
        replicas = weight_sharing_replicas(net, 2, batch_size=8)
        chunked_backward(replicas, StepBatch((x,), loss))
        return torch.cat([p.grad.flatten() for p in net.parameters()]).clone()

    assert torch.equal(run(1), run(2))
    assert torch.equal(run(1), run(4))


def test_run_tasks_keeps_order_and_one_torch_thread(outer_threads):
    outer_threads(3)
    assert budget() == 3
    seen = run_tasks(lambda i: (i, torch.get_num_threads()), range(7))
    assert [i for i, _ in seen] == list(range(7))
    assert {t for _, t in seen} == {1}
    with one_thread_per_task() as held:
        assert held == 3 and torch.get_num_threads() == 1 and budget() == 3
        with one_thread_per_task() as inner:  # nested: the outermost budget
            assert inner == 3
    assert torch.get_num_threads() == 3


def test_run_tasks_keeps_the_callers_grad_mode_and_nests_in_order(outer_threads):
    """torch keeps the grad mode per thread: the workers take the caller's; work nested in a task has a budget
    of 1 (it runs in order in that task's thread)."""
    outer_threads(2)
    w = torch.ones(3, requires_grad=True)
    with torch.no_grad():
        assert run_tasks(lambda _: (w * 2).requires_grad, range(2)) == [False, False]
    assert run_tasks(lambda _: (w * 2).requires_grad, range(2)) == [True, True]
    assert run_tasks(lambda _: budget(), range(2)) == [1, 1]


def test_group_size_caps_the_images_in_flight(outer_threads):
    outer_threads(8)
    with one_thread_per_task():
        assert group_size(torch.zeros(1, 3, 64, 64)) == 8
        big = torch.zeros(1, 3, 4000, 6000)  # 288 MB of input and output each time: one at a time
        assert group_size(big) == 1
        mid = torch.zeros(1, 3, 1200, 1600)  # 46 MB of input and output each time
        assert group_size(mid) == IN_FLIGHT_BYTES // (2 * mid.numel() * 4) == 5
    with pytest.raises(ValueError, match="passes"):
        mean_of_passes(torch.zeros(1, 3, 4, 4), 0, lambda k: None, lambda k, y: y)


def test_training_with_chunks_against_a_loop(outer_threads):
    """Reference: Adam with the warm-up and cosine schedule over 15 steps, each step's chunks backpropagated
    one after the other through the one network (gradients accumulated in chunk order), on one thread;
    `optimise_unet` on 3 threads (each chunk through its own weight-sharing replica) gives the same bits."""
    cfg = N2VConfig(unet=UNetConfig(width=8, depth=2), steps=15, batch_size=5, lr=3e-3, batch_chunks=2,
                    divergence_guard=False)
    x = torch.rand(5, 3, 32, 32, generator=torch.Generator().manual_seed(1))

    def loss(unet, y):
        return torch.mean((unet(y) - 0.5) ** 2)

    weights = []
    for reference in (False, True):
        torch.manual_seed(0)
        model = N2VModel(UNet(cfg.unet), mean=(0.0,) * 3, std=(1.0,) * 3)
        gen = torch.Generator().manual_seed(2)

        def batch_at_step(step: int, gen=gen) -> StepBatch:
            return StepBatch((x + 0.1 * torch.randn(x.shape, generator=gen),), loss)

        if not reference:
            outer_threads(3)
            optimise_unet(model, cfg, batch_at_step, desc="test")
        else:
            outer_threads(1)
            reference_training(model, cfg, batch_at_step, chunks=2)
        weights.append(torch.cat([p.detach().flatten() for p in model.unet.parameters()]))
    assert torch.equal(weights[0], weights[1])
    with pytest.raises(ConfigError, match="batch_chunks"):
        Round2Config(batch_chunks=0)


def test_mean_of_passes_against_a_loop(outer_threads):
    """Reference: draw and predict one pass after the other with the same generator."""
    x = torch.rand(1, 3, 16, 16)

    def run(threads: int, parallel: bool) -> torch.Tensor:
        outer_threads(threads)
        gen = torch.Generator().manual_seed(5)
        draw = lambda k: x + 0.1 * torch.randn(x.shape, generator=gen) + k  # noqa: E731
        predict = lambda k, y: torch.sin(y) * (k + 1)  # noqa: E731
        if parallel:
            return mean_of_passes(x, 5, draw, predict)
        acc = torch.zeros_like(x)
        for k in range(5):
            acc += predict(k, draw(k))
        return acc / 5

    reference = run(1, parallel=False)
    assert torch.equal(run(2, parallel=True), reference)
    assert torch.equal(run(3, parallel=True), reference)  # groups of 3 and 2: the sums' order matters


def test_denoising_does_not_depend_on_the_callers_threads(outer_threads, rng):
    """N2V's K-pass inference, R2R's recorrupted passes, Neighbor2Neighbor's one pass per image and the
    J-invariant prediction: the same bits with 1 and 2 caller threads, training included."""
    imgs = [add_noise(rng, smooth_scene(rng, 40, 48), 0.1) for _ in range(3)]
    results = {}
    for threads in (1, 2):
        outer_threads(threads)
        out = []
        n2v = train_n2v(imgs, N2VConfig(unet=UNetConfig(width=8, depth=2), steps=3, batch_size=4, patch_px=32), seed=0)
        out += denoise_images(n2v, imgs, passes=3, seed=1)
        for method in ("r2r", "neighbor2neighbor"):
            cfg = N2VConfig(unet=UNetConfig(width=8, depth=2), steps=3, batch_size=4, patch_px=32, method=method)
            model = train_self_supervised(imgs, cfg, seed=0)
            out += denoise_with_method(model, imgs, cfg, passes=3, seed=1)
        x = torch.from_numpy(imgs[0].transpose(2, 0, 1).copy())[None]
        out.append(jinvariant_predict(n2v, x, generator=torch.Generator().manual_seed(2)).numpy())
        results[threads] = out
    for a, b in zip(results[1], results[2], strict=True):
        np.testing.assert_array_equal(a, b)


def test_tiled_prediction_against_a_loop_and_on_threads(outer_threads, monkeypatch):
    """A photo larger than one tile: its tiles run one per task; the same bits as a written-out loop over the
    tiles on one thread, with 1, 2 or 3 caller threads; and the tiles do run on several threads."""
    model = new_model(N2VConfig(unet=UNetConfig(width=8, depth=2)), [torch.rand(3, 32, 32)], seed=0)
    model.unet.eval()
    x = torch.rand(1, 3, 70, 90, generator=torch.Generator().manual_seed(3))
    tile, margin = 24, 8

    outer_threads(1)
    reference = torch.empty_like(x)
    with torch.no_grad():
        for y0 in tile_starts(70, tile):
            for x0 in tile_starts(90, tile):
                y1, x1 = min(y0 + tile, 70), min(x0 + tile, 90)
                cy0, cx0 = max(0, y0 - margin), max(0, x0 - margin)
                cy1, cx1 = min(70, y1 + margin), min(90, x1 + margin)
                reference[..., y0:y1, x0:x1] = model.apply(x[..., cy0:cy1, cx0:cx1])[..., y0 - cy0:y1 - cy0,
                                                                                   x0 - cx0:x1 - cx0]
    seen = set()
    apply = model.apply

    def spy(inp, **kw):
        seen.add(threading.get_ident())
        assert torch.get_num_threads() == 1
        return apply(inp, **kw)

    monkeypatch.setattr(model, "apply", spy)
    for threads in (1, 2, 3):
        outer_threads(threads)
        seen.clear()
        with torch.no_grad():
            assert torch.equal(predict_tiled(model, x, tile_px=tile, margin_px=margin), reference)
        # One caller thread: the tiles in order here; more: on the worker threads.
        assert seen == {threading.get_ident()} if threads == 1 else threading.get_ident() not in seen
