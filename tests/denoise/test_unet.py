"""UNet shapes, options and the max-blur-pool against a direct reference."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from denoise.unet import MaxBlurPool2d, UNet, UNetConfig
from mvgeo.common.errors import ShapeError


@pytest.mark.parametrize("blurpool,top_skip", [(False, True), (True, False)])
@pytest.mark.parametrize("hw", [(16, 16), (37, 53), (5, 3), (2, 2)])
def test_unet_any_size(blurpool, top_skip, hw):
    net = UNet(UNetConfig(width=4, blurpool=blurpool, top_skip=top_skip))
    x = torch.rand(2, 3, *hw)
    y = net(x)
    assert y.shape == x.shape and torch.isfinite(y).all()


def test_unet_no_top_skip_has_fewer_inputs_at_top():
    a = UNet(UNetConfig(width=4))
    b = UNet(UNetConfig(width=4, top_skip=False))
    # The last decoder block sees the upsampled level-1 features (8) + the top skip (4), or only the 8.
    assert a.decoders[-1][0].in_channels == 12
    assert b.decoders[-1][0].in_channels == 8


def test_unet_widths_and_levels():
    net = UNet(UNetConfig(width=8, depth=4, max_width_mult=4))
    assert [e[0].out_channels for e in net.encoders] == [8, 16, 32, 32]
    assert net.bottleneck[0].out_channels == 32


def test_unet_padding_keeps_content_aligned():
    # Each output pixel depends on the input around it: a network that is the identity on
    # its top-level features must reproduce the input, so padding/cropping must not shift it.
    torch.manual_seed(0)
    net = UNet(UNetConfig(width=3, depth=2))
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        # Identity through the first encoder conv pair and the top skip into the head.
        enc = net.encoders[0]
        for conv in (enc[0], enc[2]):
            for c in range(3):
                conv.weight[c, c, 1, 1] = 1.0
        dec = net.decoders[-1]
        n_up = dec[0].in_channels - 3
        for c in range(3):
            dec[0].weight[c, n_up + c, 1, 1] = 1.0
            dec[2].weight[c, c, 1, 1] = 1.0
            net.head.weight[c, c, 0, 0] = 1.0
    x = torch.rand(1, 3, 13, 10)  # odd size -> padded to 16 x 12 internally
    # LeakyReLU is the identity on positive inputs, so the output is exactly the input.
    torch.testing.assert_close(net(x), x)


def test_max_blur_pool_reference(rng):
    x = torch.from_numpy(rng.random((1, 2, 8, 6))).float()
    out = MaxBlurPool2d()(x)
    # Reference: numpy stride-1 2x2 max (edge-replicated), edge-pad 1, blur, take every 2nd.
    a = x.numpy()[0]
    ap = np.pad(a, ((0, 0), (0, 1), (0, 1)), mode="edge")
    m = np.maximum.reduce([ap[:, :-1, :-1], ap[:, 1:, :-1], ap[:, :-1, 1:], ap[:, 1:, 1:]])
    mp = np.pad(m, ((0, 0), (1, 1), (1, 1)), mode="edge")
    k = np.outer([1, 2, 1], [1, 2, 1]) / 16.0
    ref = np.zeros((2, 4, 3))
    for c in range(2):
        for i in range(4):
            for j in range(3):
                ref[c, i, j] = np.sum(mp[c, 2 * i : 2 * i + 3, 2 * j : 2 * j + 3] * k)
    np.testing.assert_allclose(out[0].numpy(), ref, atol=1e-6)  # float32 sums of 9 terms
    assert out.shape[-2:] == F.max_pool2d(x, 2).shape[-2:]


def test_unet_rejects_wrong_channels():
    with pytest.raises(ShapeError):
        UNet(UNetConfig(width=4))(torch.rand(1, 1, 8, 8))
    with pytest.raises(ValueError):
        UNetConfig(width=0)


@pytest.mark.filterwarnings("ignore:TF32 acceleration")
@pytest.mark.parametrize("blurpool", [False, True])
def test_channels_last_fast_path_matches_the_nchw_reference(blurpool, monkeypatch):
    """On the CPU the UNet runs channels-last activations through oneDNN (the fast path); the reference is
    the same network on NCHW activations with oneDNN off (PyTorch's plain convolutions, pooling, upsampling).
    Outputs and every weight gradient agree to float32 round-off: 1e-5 relative to the largest value (the
    widest convolution sums 9 x 96 products)."""
    import denoise.unet as unet_module

    torch.manual_seed(0)
    net = UNet(UNetConfig(width=8, depth=3, blurpool=blurpool))
    x = torch.rand(2, 3, 40, 56)
    target = torch.rand(2, 3, 40, 56)

    def run():
        net.zero_grad()
        out = net(x)
        ((out - target) ** 2).mean().backward()
        return out.detach().clone(), [p.grad.clone() for p in net.parameters()]

    out, grads = run()
    assert out.is_contiguous()  # callers get the usual NCHW layout back
    monkeypatch.setattr(unet_module, "_CHANNELS_LAST_ON_CPU", False)
    with torch.backends.mkldnn.flags(enabled=False):
        ref_out, ref_grads = run()
    assert torch.allclose(out, ref_out, atol=1e-5 * float(ref_out.abs().max()), rtol=0)
    for g, r in zip(grads, ref_grads, strict=True):
        assert torch.allclose(g, r, atol=1e-5 * float(r.abs().max()), rtol=0)
