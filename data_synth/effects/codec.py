"""Encoding effects: JPEG compression and integer quantisation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data_synth.effects.registry import EffectContext, register_effect
from data_synth.schema import spec_field
from mvgeo.common.deps import cv2
from mvgeo.common.imageio import to_uint


@dataclass(frozen=True)
class JpegParams:
    quality: int = spec_field(75, range=(1, 100), doc="libjpeg quality")


@register_effect("jpeg", JpegParams)
def jpeg(image: np.ndarray, params: JpegParams, ctx: EffectContext, rng: np.random.Generator) -> np.ndarray:
    """Round trip through an 8-bit JPEG at `quality` (4:2:0 chroma subsampling, OpenCV's default)."""
    bgr = np.ascontiguousarray(to_uint(image, 8)[:, :, ::-1])
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(params.quality)])
    if not ok:
        raise RuntimeError("OpenCV failed to encode a JPEG")
    dec = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return np.ascontiguousarray(dec[:, :, ::-1]).astype(np.float32) / np.float32(255.0)


@dataclass(frozen=True)
class QuantizeParams:
    bits: int = spec_field(8, range=(1, 16), doc="bits per channel")


@register_effect("quantize", QuantizeParams)
def quantize(image: np.ndarray, params: QuantizeParams, ctx: EffectContext, rng: np.random.Generator) -> np.ndarray:
    """Clip to [0, 1] and round to 2^bits - 1 levels (round half to even), in float64: a float32 product rounds
    about one value in 1e5 (8 bits) to 1e3 (16 bits) to the neighbouring level first."""
    levels = float(2**params.bits - 1)
    x = np.clip(np.asarray(image, np.float64), 0.0, 1.0)
    return (np.rint(x * levels) / levels).astype(np.float32)
