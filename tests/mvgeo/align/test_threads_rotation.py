"""Native-thread limiter (restores the settings) and dense flow for upside-down pairs."""

import numpy as np

from mvgeo.align.classical_pairs import _flow_rotated_180, dense_flow
from mvgeo.common.deps import cv2
from mvgeo.common.threads import blas_thread_counts, native_threads


def test_native_threads_limits_and_restores():
    before, cv_before = blas_thread_counts(), cv2.getNumThreads()
    assert before  # numpy's OpenBLAS is loaded in this process (Linux wheels)
    with native_threads(1):
        assert blas_thread_counts() == [1] * len(before)
        assert cv2.getNumThreads() == 1
    assert blas_thread_counts() == before and cv2.getNumThreads() == cv_before


def _textured(H, W, seed=0):
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur((rng.random((H, W)) * 255).astype(np.float32), (0, 0), 1.5)
    return cv2.normalize(g, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def test_flow_of_an_upside_down_pair_is_the_exact_180_degree_map():
    H, W = 48, 64
    a = _textured(H, W)
    b = np.ascontiguousarray(a[::-1, ::-1])  # b = a turned by 180 deg: pixel p of a sits at (W, H) - p in b
    rng = np.random.default_rng(1)
    uv_a = rng.uniform(4, [W - 4, H - 4], size=(60, 2))
    uv_b = np.array([W, H]) - uv_a
    f_ab, f_ba = _flow_rotated_180(a, b, uv_a, uv_b)
    v, u = np.mgrid[0:H, 0:W] + 0.5
    p = np.stack([u, v], -1)
    exact = (np.array([W, H]) - p) - p  # the same map both ways
    inner = (slice(4, H - 4), slice(4, W - 4))
    # DIS on a textured image with exact initialisation: sub-pixel (measured median < 0.05 px);
    # 0.5 px leaves room for OpenCV versions. The plain flow must be far off (the case this handles).
    assert np.median(np.linalg.norm(f_ab[inner] - exact[inner], axis=-1)) < 0.5
    assert np.median(np.linalg.norm(f_ba[inner] - exact[inner], axis=-1)) < 0.5
    plain = dense_flow(a, b, uv_a, uv_b)
    assert np.median(np.linalg.norm(plain[inner] - exact[inner], axis=-1)) > 2.0
