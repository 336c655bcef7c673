"""Dense two-view correspondences and pointmaps of the classical pair model.

The inlier matches are densified with OpenCV's edge-aware interpolator (EpicFlow) and refined by DIS
optical flow, both ways (`pair_flows`); `flow_checks` measures each pixel's forward-backward error and
epipolar (Sampson) distance; `pair_pointmap` triangulates the pixels that pass
(`mvgeo.triangulate.triangulate_two_view`) and gives each a confidence >= 1 (1: unknown, placeholder
depth); `pair_pointmap_reference` triangulates every pixel and masks afterwards (the tests' reference).
Pixel convention: docs/conventions.md.
"""

from __future__ import annotations

import numpy as np

from mvgeo.common.deps import cv2
from mvgeo.epipolar import sampson_distance
from mvgeo.triangulate import triangulate_two_view

__all__ = ["dense_flow", "flow_checks", "pair_flows", "pair_pointmap", "pair_pointmap_reference", "quarter_turns"]


def _resize(image: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    if image.shape[:2] == hw:
        return image
    return cv2.resize(image, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)


_MIN_INTERPOLATOR_MATCHES = 8


def dense_flow(gray_a: np.ndarray, gray_b: np.ndarray, uv_a_px: np.ndarray, uv_b_px: np.ndarray) -> np.ndarray:
    """(H, W, 2) flow a -> b: sparse matches densified (edge-aware), refined by DIS.

    Args:
        gray_a, gray_b: (H, W) uint8 images of the same size.
        uv_a_px, uv_b_px: (M, 2) matches in our pixel convention at this resolution.
    """
    H, W = gray_a.shape
    # OpenCV pixel centres sit at integers: ours - 0.5 (docs/conventions.md).
    src = (uv_a_px - 0.5).astype(np.float32)
    dst = (uv_b_px - 0.5).astype(np.float32)
    inside = (src[:, 0] >= 0) & (src[:, 0] <= W - 1) & (src[:, 1] >= 0) & (src[:, 1] <= H - 1)
    src, dst = src[inside], dst[inside]
    # OpenCV's EdgeAwareInterpolator segfaults (measured: 2 of 3 runs on a real pair) when two
    # matches fall on the same integer pixel (SIFT returns one keypoint per orientation, so exact
    # duplicates are common) or when it gets very few matches. Keep one match per pixel, and
    # below a handful fall back to the median displacement as the initial flow.
    _, first = np.unique(np.rint(src).astype(np.int64) @ np.array([1, W + 1]), return_index=True)
    src, dst = src[np.sort(first)], dst[np.sort(first)]
    if len(src) < _MIN_INTERPOLATOR_MATCHES:
        shift = np.median(dst - src, axis=0) if len(src) else np.zeros(2, np.float32)
        init = np.broadcast_to(shift.astype(np.float32), (H, W, 2))
    else:
        interp = cv2.ximgproc.createEdgeAwareInterpolator()
        interp.setK(min(32, len(src) - 1))
        init = interp.interpolate(cv2.cvtColor(gray_a, cv2.COLOR_GRAY2BGR), src.reshape(-1, 1, 2),
                                  cv2.cvtColor(gray_b, cv2.COLOR_GRAY2BGR), dst.reshape(-1, 1, 2))
    dis = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(gray_a, gray_b, np.ascontiguousarray(init, dtype=np.float32))


def _turn_points(uv_px: np.ndarray, k: int, wh: tuple[int, int]) -> np.ndarray:
    """Pixels (our convention) of a W x H image as pixels of ``np.rot90(image, k)`` (k quarter turns
    counter-clockwise): one turn maps (u, v) to (v, W - u)."""
    W, H = wh
    uv = np.asarray(uv_px, np.float32)
    for _ in range(k % 4):
        uv = np.stack([uv[..., 1], W - uv[..., 0]], -1)
        W, H = H, W
    return uv


def _flow_turned(gray_a, gray_b, uv_a_px, uv_b_px, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Flows a -> b and b -> a when b's image plane is turned by `k` quarter turns relative to a's (a camera
    held sideways, k = 1 or 3; a camera on the far side of a ring, k = 2: DIS flow, which searches small
    displacements coarse to fine, finds nothing there). Flow against ``np.rot90(b, k)`` on a canvas both
    fit in (zero-padded at the bottom and right, which keeps every pixel's coordinates), then express both
    flows in b's own pixels."""
    H, W = gray_b.shape
    Ha, Wa = gray_a.shape
    b_rot = np.ascontiguousarray(np.rot90(gray_b, k))
    Hr, Wr = b_rot.shape
    Hc, Wc = max(Ha, Hr), max(Wa, Wr)

    def canvas(g):
        out = np.zeros((Hc, Wc), g.dtype)
        out[:g.shape[0], :g.shape[1]] = g
        return out

    uv_b_rot = _turn_points(uv_b_px, k, (W, H))
    f_ab_rot = dense_flow(canvas(gray_a), canvas(b_rot), uv_a_px, uv_b_rot)[:Ha, :Wa]
    f_ba_rot = dense_flow(canvas(b_rot), canvas(gray_a), uv_b_rot, uv_a_px)[:Hr, :Wr]
    va, ua = np.mgrid[0:Ha, 0:Wa].astype(np.float32) + 0.5
    pa = np.stack([ua, va], -1)
    # a -> b: the target in turned b, turned back (the inverse of k turns is 4 - k turns of the turned image).
    flow_ab = _turn_points(pa + f_ab_rot, (4 - k) % 4, (Wr, Hr)) - pa
    # b -> a at b's pixel p: the turned image's pixel of p holds its flow; turning that grid back puts it at p.
    vb, ub = np.mgrid[0:H, 0:W].astype(np.float32) + 0.5
    pb = np.stack([ub, vb], -1)
    flow_ba = np.rot90(f_ba_rot, -k) + _turn_points(pb, k, (W, H)) - pb
    return np.ascontiguousarray(flow_ab, np.float32), np.ascontiguousarray(flow_ba, np.float32)


def quarter_turns(R_b_from_a: np.ndarray) -> int:
    """Quarter turns (0-3, counter-clockwise in b's image) that bring b's image plane nearest a's: the relative
    rotation's turn of the image plane rounded to 90 deg (the only way `pair_flows` depends on the rotation)."""
    roll = np.degrees(np.arctan2(R_b_from_a[1, 0], R_b_from_a[0, 0]))
    return int(np.round(roll / 90.0)) % 4


def pair_flows(gray_a: np.ndarray, gray_b: np.ndarray, uv_a_px: np.ndarray, uv_b_px: np.ndarray,
               R_b_from_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flows a -> b and b -> a ((H, W, 2) each) seeded by the matches; against b turned by quarter turns when
    the relative rotation `R_b_from_a` turns the image plane by more than 45 deg (`quarter_turns`)."""
    k = quarter_turns(R_b_from_a)
    if k:
        return _flow_turned(gray_a, gray_b, uv_a_px, uv_b_px, k)
    return dense_flow(gray_a, gray_b, uv_a_px, uv_b_px), dense_flow(gray_b, gray_a, uv_b_px, uv_a_px)


def flow_checks(flow_ab, flow_ba, Ka, Kb, F_ab):
    """Per pixel of view a (row-major): forward-backward flow error, target inside view b, Sampson
    distance to F_ab, and the rays of the pixel and of its flow target (camera frames)."""
    H, W = flow_ab.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    ua = np.stack([u, v], -1).reshape(-1, 2)
    ub = ua + flow_ab.reshape(-1, 2)
    # Backward flow sampled at the forward target (bilinear; OpenCV centres at integers).
    back = cv2.remap(flow_ba, (ub[:, 0] - 0.5).astype(np.float32).reshape(H, W),
                     (ub[:, 1] - 0.5).astype(np.float32).reshape(H, W), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=(1e6, 1e6))
    d = flow_ab.reshape(-1, 2) + back.reshape(-1, 2)
    fb = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])  # = np.linalg.norm(d, axis=1), faster on 2-long rows
    inside = (ub[:, 0] > 0) & (ub[:, 0] < W) & (ub[:, 1] > 0) & (ub[:, 1] < H)
    sampson = sampson_distance(F_ab, ua, ub)
    rays_a = np.concatenate([ua, np.ones((len(ua), 1))], 1) @ np.linalg.inv(Ka).T
    rays_b = np.concatenate([ub, np.ones((len(ub), 1))], 1) @ np.linalg.inv(Kb).T
    return fb, inside, sampson, rays_a, rays_b



def _confidence(fb, angle_deg, sampson, config) -> np.ndarray:
    """1 + conf_max x forward-backward term x triangulation-angle term x epipolar term."""
    return 1.0 + config.conf_max * (np.exp(-0.5 * (fb / (0.5 * config.fb_max_px)) ** 2)
                                    * np.minimum(angle_deg / config.angle_ref_deg, 1.0)
                                    * np.exp(-0.5 * (sampson / (0.5 * config.epipolar_max_px)) ** 2))


def _fill_placeholder(pts: np.ndarray, ok: np.ndarray, rays_a: np.ndarray) -> np.ndarray:
    """Pixels without a valid point get their ray at the median depth of the valid ones (depth 1 if none)."""
    if np.any(ok):
        pts[~ok] = rays_a[~ok] / rays_a[~ok, 2:3] * float(np.median(pts[ok, 2]))
        return pts
    return rays_a / rays_a[:, 2:3]


def pair_pointmap(flow_ab, flow_ba, Ka, Kb, F_ab, cam_b_from_a, config) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) points of view a's pixels in frame a and (H, W) confidence, from the flows a <-> b.

    Only the pixels that pass the cheap checks (inside b, forward-backward below `fb_max_px`, Sampson
    distance below `epipolar_max_px`) are triangulated; the others get confidence 1 and the placeholder
    depth whatever their triangulation (rows are independent: the same values as
    `pair_pointmap_reference`). `config`: `ClassicalPairConfig`.
    """
    H, W = flow_ab.shape[:2]
    fb, inside, sampson, rays_a, rays_b = flow_checks(flow_ab, flow_ba, Ka, Kb, F_ab)
    pre = np.flatnonzero(inside & (fb < config.fb_max_px) & (sampson < config.epipolar_max_px))
    tri = triangulate_two_view(rays_a[pre], rays_b[pre], cam_b_from_a, criteria=config.triangulation)
    sel = pre[tri.valid]
    ok = np.zeros(len(rays_a), bool)
    ok[sel] = True
    conf = np.ones(len(rays_a))
    conf[sel] = _confidence(fb[sel], tri.angle_deg[tri.valid], sampson[sel], config)
    pts = np.empty((len(rays_a), 3))
    pts[sel] = tri.points[tri.valid]
    return _fill_placeholder(pts, ok, rays_a).reshape(H, W, 3), conf.reshape(H, W)


def pair_pointmap_reference(flow_ab, flow_ba, Ka, Kb, F_ab, cam_b_from_a, config) -> tuple[np.ndarray, np.ndarray]:
    """Slow, obvious `pair_pointmap`: triangulates every pixel, then masks (the tests' reference)."""
    H, W = flow_ab.shape[:2]
    fb, inside, sampson, rays_a, rays_b = flow_checks(flow_ab, flow_ba, Ka, Kb, F_ab)
    tri = triangulate_two_view(rays_a, rays_b, cam_b_from_a, criteria=config.triangulation)
    ok = inside & (fb < config.fb_max_px) & (sampson < config.epipolar_max_px) & tri.valid
    conf = np.where(ok, _confidence(fb, tri.angle_deg, sampson, config), 1.0)
    pts = _fill_placeholder(tri.points.copy(), ok, rays_a)
    return pts.reshape(H, W, 3), conf.reshape(H, W)
