"""Grouped empirical Wiener refinement: similar patches of a photo denoised together, with a pilot's statistics.

The sliding-window DCT step (`denoise.wiener`) shrinks each block of the noisy photo on its own. Natural
photos repeat themselves (bricks, tiles, a roof's texture), so a patch's noise can also be averaged with the
patches that look like it. Here, for every reference patch on a grid:

1. the ``n`` patches most like it within a search window are found on the *pilot* (a denoised photo: its
   distances are not dominated by noise);
2. the pilot's patches of that group give the group's signal covariance ``C`` (``d x d``, ``d = p^2 x 3``);
3. each noisy patch of the group is estimated by the linear MMSE (Wiener) filter of that Gaussian model,
   ``x = m + C (C + S)^-1 (y - m)``, ``S`` the noise covariance (diagonal: the group's mean pixel variance
   per channel), ``m`` the mean of the group's noisy patches (unbiased where the noise is), or the pilot's
   mean where more than `GroupedWienerConfig.clipped_share` of the group's noisy values sit at 0 or 1 (the
   clipped photo's mean is biased there; the pilot has been through the clipped-noise inverse);
4. every estimated patch of every group is averaged into the output, pixel by pixel.

This is the second step of the non-local Bayes denoiser (Lebrun, Buades and Morel, "A nonlocal Bayesian
image denoising algorithm", SIAM J. Imaging Sciences 2013), here with a learned pilot instead of the
first step's estimate. Colour photos are worked on in the orthonormal opponent space of `denoise.wiener`
(independent per-channel noise stays independent), patches holding all three channels.

Measured on DTU scan24 at sigma 25/255 (the `default` preset's photos after the DCT step as pilots):
docs/bench/denoise_real.md, "The grouped Wiener step".
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from denoise.wiener import OPPONENT, block_origins

__all__ = ["GroupedWienerConfig", "grouped_wiener", "pass_configs", "search_offsets"]


@dataclass(frozen=True)
class GroupedWienerConfig:
    """The grouped Wiener step.

    Attributes:
        patch_px: patch side ``p`` (NL-Bayes uses 5 for colour photos at sigma 20-50).
        search_radius_px: similar patches are looked for within ``+-radius`` px of the reference.
        group_size: patches per group ``n`` (the reference and its ``n - 1`` nearest on the pilot).
        stride_px: distance between reference patches (every pixel is covered: the last row and column of
            references end at the photo's edge).
        clipped_share: above this share of the group's noisy values at 0 or 1, the group's mean is the
            pilot's instead of the noisy patches'.
        groups_per_chunk: groups processed together (bounds memory: a chunk holds about
            ``groups_per_chunk * d^2`` floats of covariance, ``d = 3 p^2``).
        passes: how many times the denoise stage runs the step, each pass with the previous one's output
            as its pilot (`denoise.self_supervised`; this module's `grouped_wiener` is one pass).
        later_group_size: patches per group in the passes after the first. A better pilot finds better
            groups, and larger ones pay: on the `default` preset's photos of four real sets a second pass
            gains +0.14 to +0.28 dB with 80 patches, and -0.08 to +0.22 with 40 (docs/bench/denoise_real.md,
            "A second grouped pass").
    """

    patch_px: int = 5
    search_radius_px: int = 10
    group_size: int = 40
    stride_px: int = 3
    clipped_share: float = 0.2
    groups_per_chunk: int = 1024
    passes: int = 1
    later_group_size: int = 80

    def __post_init__(self):
        if self.patch_px < 1 or self.search_radius_px < 0 or self.stride_px < 1 or self.groups_per_chunk < 1:
            raise ValueError(f"invalid GroupedWienerConfig {self}: need patch_px >= 1, search_radius_px >= 0, "
                             "stride_px >= 1, groups_per_chunk >= 1")
        if not 2 <= self.group_size <= (2 * self.search_radius_px + 1) ** 2:
            raise ValueError(f"invalid GroupedWienerConfig {self}: group_size must be in [2, (2 * radius + 1)^2]")
        if self.passes < 1:
            raise ValueError(f"invalid GroupedWienerConfig {self}: passes must be >= 1")
        if self.passes > 1 and not 2 <= self.later_group_size <= (2 * self.search_radius_px + 1) ** 2:
            raise ValueError(f"invalid GroupedWienerConfig {self}: later_group_size must be in [2, (2 * radius + 1)^2]")
        if not 0.0 <= self.clipped_share <= 1.0:
            raise ValueError(f"invalid GroupedWienerConfig {self}: clipped_share must be in [0, 1]")


def pass_configs(config: GroupedWienerConfig) -> list[GroupedWienerConfig]:
    """One single-pass config per pass of `config`: the first as given, the later ones with
    `later_group_size` patches per group."""
    one = replace(config, passes=1)
    return [one] + [replace(one, group_size=config.later_group_size) for _ in range(config.passes - 1)]


def search_offsets(radius: int) -> np.ndarray:
    """``(K, 2)`` int offsets ``(dy, dx)`` of the search window, row-major; ``(0, 0)`` at index ``K // 2``."""
    r = np.arange(-radius, radius + 1)
    dy, dx = np.meshgrid(r, r, indexing="ij")
    return np.stack([dy.ravel(), dx.ravel()], axis=1)


def _window_sums(a: np.ndarray, block: int) -> np.ndarray:
    """Sum of the ``(h, w)`` array `a` over every ``block x block`` window, ``(h - block + 1, w - block + 1)``,
    by ``2 * block`` shifted additions (rows, then columns). The sum of a window depends only on the values
    in it, not on where the window lies: translated windows of the same values give the same bits (an
    integral image's differences do not), which `_patch_distances`' symmetry relies on."""
    h, w = a.shape
    rows = a[:h - block + 1].copy()
    for i in range(1, block):
        rows += a[i:h - block + 1 + i]
    out = rows[:, :w - block + 1].copy()
    for j in range(1, block):
        out += rows[:, j:w - block + 1 + j]
    return out


def _patch_distances(pilot: np.ndarray, ref_y: np.ndarray, ref_x: np.ndarray, patch: int,
                     offsets: np.ndarray) -> np.ndarray:
    """``(R, K)`` squared distances between each reference patch of `pilot` ``(H, W, C)`` and the patch at
    each offset (``inf`` where that patch leaves the photo).

    The distances at offset ``o`` and at ``-o`` are the same patch pairs seen from either end: the
    pixel-wise squared differences of ``o`` are computed once, and the reference ``r``'s distance at ``-o``
    is the window sum of ``o``'s at ``r - o``. In `search_offsets`' order offset ``K - 1 - k`` is ``-offsets[k]``,
    so the first half (and the centre) are computed."""
    if not np.array_equal(offsets[::-1], -offsets):
        raise ValueError("offsets must be ordered as search_offsets orders them (offsets[K - 1 - k] = -offsets[k])")
    H, W = pilot.shape[:2]
    K = len(offsets)
    dist = np.full((len(ref_y), K), np.inf, np.float32)
    # Window sums are read from a frame of inf `reach` px wide on every side: a patch partly outside the
    # photo reads inf, the reference's distance to it.
    reach = int(np.abs(offsets).max()) if len(offsets) else 0
    frame = np.full((H + 2 * reach, W + 2 * reach), np.inf)

    for k in range((K + 1) // 2):
        dy, dx = (int(v) for v in offsets[k])
        mirror = K - 1 - k
        # Pixel-wise squared difference between (i, j) and (i + dy, j + dx), where both are inside.
        y0, y1, x0, x1 = max(0, -dy), min(H, H - dy), max(0, -dx), min(W, W - dx)
        if y1 - y0 < patch or x1 - x0 < patch:  # no patch at this offset stays inside the photo
            continue
        diff = pilot[y0:y1, x0:x1] - pilot[y0 + dy:y1 + dy, x0 + dx:x1 + dx]
        box = _window_sums(np.einsum("ijc,ijc->ij", diff, diff), patch)  # entry (i, j): origin (y0 + i, x0 + j)
        # The frame holds o's window sums at their origins, inf at every origin where the pair (r, r + o)
        # leaves the photo.
        frame.fill(np.inf)
        frame[reach + y0:reach + y0 + box.shape[0], reach + x0:reach + x0 + box.shape[1]] = box
        dist[:, k] = frame[reach + ref_y, reach + ref_x]
        if mirror != k:  # the pair (r, r - o) is the pair (r - o, r) of offset o: o's sum at origin r - o
            dist[:, mirror] = frame[reach + ref_y - dy, reach + ref_x - dx]
    return dist


def grouped_wiener(noisy: np.ndarray, pilot: np.ndarray, sigma: float | np.ndarray,
                   config: GroupedWienerConfig = GroupedWienerConfig()) -> np.ndarray:
    """The noisy photo denoised group by group with the pilot's statistics (module docstring).

    Args:
        noisy: ``(H, W, 3)`` RGB or ``(H, W)`` gray in ``[0, 1]`` (values at 0 and 1 count as clipped); three
            equal channels (a gray photo read as RGB) are filtered as gray, with the mean of the pilot's channels,
            and returned in three channels.
        pilot: the same photo denoised, same shape.
        sigma: the noise std: one number, or per pixel (and channel) in the shape of `noisy`.
        config: `GroupedWienerConfig`.

    Returns:
        The refined photo, float32, the shape of `noisy` (not clipped). Photos smaller than a patch come back as the
        pilot.
    """
    y_in = np.asarray(noisy, np.float64)
    p_in = np.asarray(pilot, np.float64)
    if y_in.shape != p_in.shape or not (y_in.ndim == 2 or (y_in.ndim == 3 and y_in.shape[2] == 3)):
        raise ValueError(f"noisy {y_in.shape} and pilot {p_in.shape} must both be (H, W, 3) or (H, W)")
    gray = y_in.ndim == 2
    if not gray and (y_in == y_in[..., :1]).all():
        # A gray photo read as RGB: the same noise in every channel, not the independent noise of the opponent
        # space. Filtered as the gray photo (the pilot's channels' mean, the noise's RMS over the channels).
        sig = np.asarray(sigma, np.float64)
        out = grouped_wiener(y_in[..., 0], p_in.mean(axis=2),
                             sig if sig.ndim < 3 else np.sqrt(np.mean(sig ** 2, axis=2)), config)
        return np.repeat(out[..., None], 3, axis=2)
    # Colour: the opponent space, where each channel's variance is the OPPONENT-squared mix of the RGB ones.
    to_work = np.ones((1, 1)) if gray else OPPONENT
    y_rgb, p_rgb = (y_in[..., None], p_in[..., None]) if gray else (y_in, p_in)
    H, W, C = y_rgb.shape
    p = config.patch_px
    if H < p or W < p:
        return p_in.astype(np.float32)
    y = y_rgb @ to_work.T
    b = p_rgb @ to_work.T
    sig = np.asarray(sigma, np.float64)
    var = np.broadcast_to((sig[..., None] if gray and sig.ndim == 2 else sig) ** 2, (H, W, C)) @ (to_work ** 2).T
    # Floored at (1e-3)^2, a quarter of an 8-bit level: the groups' covariances are rank-deficient (fewer
    # patches than dimensions; none at all where the pilot is flat) and float32, so the noise term is what
    # keeps the Cholesky factorisation positive definite. A noise-free photo comes back as it is.
    var = np.maximum(var, 1e-6)

    ref_y, ref_x = (a.ravel() for a in np.meshgrid(block_origins(H, p, config.stride_px),
                                                   block_origins(W, p, config.stride_px), indexing="ij"))
    offsets = search_offsets(config.search_radius_px)
    dist = _patch_distances(b, ref_y, ref_x, p, offsets)
    dist[:, len(offsets) // 2] = -1.0  # the reference is always in its own group, ties or not
    n = config.group_size
    chosen = np.argpartition(dist, n - 1, axis=1)[:, :n]
    # A photo smaller than the search window has fewer candidates than `n` near its edges: the patches
    # outside it are replaced by the reference itself.
    outside = ~np.isfinite(np.take_along_axis(dist, chosen, axis=1))
    chosen[outside] = len(offsets) // 2

    dy, dx = np.meshgrid(np.arange(p), np.arange(p), indexing="ij")
    within = torch.from_numpy(dy.ravel() * W + dx.ravel())  # a patch's pixels from its origin, flat (row-major)
    # Per patch origin: the patch's mean noise variance per channel and its count of clipped values (over the
    # channels); a group's are the means and the sum of its patches' (all patches have p^2 pixels).
    v_win = np.zeros((H, W, C))
    c_win = np.zeros((H, W))
    clipped = ((y_rgb <= 0.0) | (y_rgb >= 1.0)).sum(axis=2).astype(np.float64)  # values, not pixels
    for c in range(C):
        v_win[:H - p + 1, :W - p + 1, c] = _window_sums(var[..., c], p) / (p * p)
    c_win[:H - p + 1, :W - p + 1] = _window_sums(clipped, p)
    # Groups in float32 (the covariance is regularised by the noise's, at least 1e-6 per pixel and usually
    # ~1e-3: well conditioned), sums in float64.
    y_f = torch.from_numpy(y.astype(np.float32).reshape(H * W, C))
    b_f = torch.from_numpy(b.astype(np.float32).reshape(H * W, C))
    v_f = torch.from_numpy(v_win.astype(np.float32).reshape(H * W, C))
    c_f = torch.from_numpy(c_win.reshape(H * W))
    num = torch.zeros((H * W, C), dtype=torch.float64)
    den = torch.zeros(H * W, dtype=torch.float64)
    d = p * p * C
    for c0 in range(0, len(ref_y), config.groups_per_chunk):
        rows = slice(c0, c0 + config.groups_per_chunk)
        origin = torch.from_numpy((ref_y[rows, None] + offsets[chosen[rows], 0]) * W
                                  + ref_x[rows, None] + offsets[chosen[rows], 1])  # (r, n) patch origins, flat
        r = origin.shape[0]
        flat = (origin[:, :, None] + within).reshape(-1)  # (r * n * p^2) pixels
        Y = y_f[flat].reshape(r, n, d)  # (r, n, p^2, C) -> (r, n, d), pixel-major
        B = b_f[flat].reshape(r, n, d)
        noise_var = v_f[origin].mean(dim=1)  # (r, C): the group's mean variance per channel
        S = noise_var[:, None, :].expand(r, p * p, C).reshape(r, d)
        mean_b = B.mean(dim=1, keepdim=True)
        Bc = B - mean_b
        share = c_f[origin].sum(dim=1) / (n * d)  # the share of the group's noisy values at 0 or 1
        mean = torch.where((share > config.clipped_share)[:, None, None], mean_b, Y.mean(dim=1, keepdim=True))
        X = mean + _wiener_rows(Y - mean, Bc, S)
        num.index_add_(0, flat, X.reshape(-1, C).to(torch.float64))
        den.index_add_(0, flat, torch.ones(flat.numel(), dtype=torch.float64))
    out = (num / den[:, None]).reshape(H, W, C).numpy() @ to_work
    return (out[..., 0] if gray else out).astype(np.float32)


def _wiener_rows(Yc: torch.Tensor, Bc: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
    """``(Y - m) (C + S)^-1 C`` per group: the centred noisy patches `Yc` ``(r, n, d)`` as rows through the
    Wiener gain of the pilot's covariance ``C = Bc^T Bc / (n - 1)`` (`Bc`: the centred pilot patches,
    ``(r, n, d)``) and the diagonal noise covariance `S` ``(r, d)``; row vectors, both matrices symmetric.

    With fewer patches than dimensions (``n < d``: colour groups, 40 patches of 75 values) ``C`` has rank at
    most ``n - 1`` and the gain is solved in the group's ``n``-dimensional space instead (the push-through
    identity): with ``A = Bc / sqrt(n - 1)``, ``(A^T A + S)^-1 A^T A = S^-1 A^T (I + A S^-1 A^T)^-1 A``.
    Both ways factor a matrix of the same condition number, ``1 + lambda_max(C) / min(S)``; the ``n x n``
    one costs about half the arithmetic and a solve with ``n`` instead of ``d`` right-hand sides (the
    step measured in docs/bench/denoise_wiener_speed.md). Otherwise the ``d x d`` system is solved directly.
    """
    n, d = Bc.shape[1], Bc.shape[2]
    if n < d:
        A = Bc / float(np.sqrt(n - 1))
        A_s = A / S[:, None, :]  # A S^-1
        M = A_s @ A.transpose(1, 2)  # A S^-1 A^T, (r, n, n)
        M.diagonal(dim1=1, dim2=2).add_(1.0)
        Z = Yc @ A_s.transpose(1, 2)  # (Y - m) S^-1 A^T, (r, n, n)
        # Z M^-1 = (M^-1 Z^T)^T, M symmetric.
        return torch.cholesky_solve(Z.transpose(1, 2), torch.linalg.cholesky(M)).transpose(1, 2) @ A
    cov = Bc.transpose(1, 2) @ Bc / (n - 1)
    chol = torch.linalg.cholesky(cov + torch.diag_embed(S))
    return Yc @ torch.cholesky_solve(cov, chol)  # (C + S)^-1 C
