"""mvgeo: what accuracy costs in time.

1. Triangulation: error vs time of our methods (mid2, midpoint, DLT, 2-view
   refined) and the references (cv2.triangulatePoints, mrcal mid2) on noisy
   pixel observations over a range of triangulation angles.
2. Relative-pose RANSAC: iteration cap vs success rate and pose error at
   several inlier ratios, our 5-point LO-MSAC vs OpenCV's findEssentialMat
   (USAC_MAGSAC and plain RANSAC) on the same seeded inputs.

Synthetic data only (no ../shared/data needed). Run: .venv/bin/python benchmarks/bench_mvgeo.py
"""

from __future__ import annotations

import os
import platform
import time

import mrcal
import numpy as np
from _common import md_table, peak_rss_mb, time_call, write_fragment  # sets sys.path to the repo root

from mvgeo import transforms as tf
from mvgeo.common.deps import cv2
from mvgeo.metrics import rotation_error_deg, translation_direction_error_deg
from mvgeo.ransac import RansacConfig
from mvgeo.triangulate import TriangulationCriteria, triangulate_multiview, triangulate_two_view
from mvgeo.twoview import TwoViewConfig, estimate_relative_pose

F_PX = 500.0
NOISE_PX = 0.5
W, H = 640, 480
K = np.array([[F_PX, 0, W / 2], [0, F_PX, H / 2], [0, 0, 1.0]])


def triangulation_section(rng: np.random.Generator) -> str:
    n = 5000
    depth = 5.0
    rows = []
    lax = TriangulationCriteria(min_angle_deg=0.0, max_angular_error_deg=180.0, max_range=1e12)
    for angle_deg in (0.5, 1.0, 2.0, 5.0, 10.0, 30.0):
        # Camera 2 on a circle around the point cloud centre, so rays meet at ~angle_deg.
        a = np.radians(angle_deg)
        C2 = np.array([depth * np.sin(a), 0.0, depth - depth * np.cos(a)])
        R2 = tf.so3_exp([0.0, -a, 0.0])
        T = np.c_[R2, -R2 @ C2]
        X = rng.uniform(-0.5, 0.5, (n, 3)) + [0, 0, depth]
        X2 = X @ R2.T + T[:, 3]
        x1 = X[:, :2] / X[:, 2:] + rng.normal(scale=NOISE_PX / F_PX, size=(n, 2))
        x2 = X2[:, :2] / X2[:, 2:] + rng.normal(scale=NOISE_PX / F_PX, size=(n, 2))
        r1 = np.c_[x1, np.ones(n)]
        r2 = np.c_[x2, np.ones(n)]
        Rt01 = np.ascontiguousarray(np.vstack([R2.T, -R2.T @ T[:, 3]]))
        methods = {
            "ours mid2": lambda r1=r1, r2=r2, T=T: triangulate_two_view(r1, r2, T, method="mid2", criteria=lax).points,
            "ours midpoint": lambda r1=r1, r2=r2, T=T: triangulate_two_view(r1, r2, T, method="midpoint",
                                                                            criteria=lax).points,
            "ours DLT": lambda r1=r1, r2=r2, T=T: triangulate_two_view(r1, r2, T, method="dlt", criteria=lax).points,
            "ours DLT+angular GN": lambda r1=r1, r2=r2, T=T: triangulate_multiview(
                np.stack([r1, r2]), np.stack([np.eye(4)[:3], T]), criteria=lax).points,
            "cv2.triangulatePoints": lambda x1=x1, x2=x2, T=T: _cv_tri(x1, x2, T),
            "mrcal mid2": lambda r1=r1, r2=r2, Rt01=Rt01: mrcal.triangulate_leecivera_mid2(
                r1, r2, Rt01=Rt01, v_are_local=True),
        }
        for name, fn in methods.items():
            P = fn()
            secs = time_call(fn, repeat=3, warmup=1)
            err3d = np.linalg.norm(P - X, axis=1) / depth
            P2 = P @ R2.T + T[:, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                rep = np.maximum(
                    np.linalg.norm(P[:, :2] / P[:, 2:] - x1, axis=1), np.linalg.norm(P2[:, :2] / P2[:, 2:] - x2, axis=1)
                ) * F_PX
            rows.append([f"{angle_deg:g}", name, float(np.median(err3d) * 100), float(np.nanmedian(rep)),
                         float(secs / n * 1e6)])
    body = (
        f"{n} points at depth ~{depth} (units), two views, {NOISE_PX} px Gaussian noise at f = {F_PX:g} px. "
        "3-D error is relative to depth; 2-D error is the larger of the two reprojection errors (px). "
        "Validity thresholds disabled here so every method's raw output is compared.\n\n"
    )
    return body + md_table(
        ["angle (deg)", "method", "median 3-D error (% of depth)", "median max reproj. (px)", "time (us/point)"], rows
    )


def _cv_tri(x1: np.ndarray, x2: np.ndarray, T: np.ndarray) -> np.ndarray:
    Xh = cv2.triangulatePoints(np.eye(4)[:3], T, x1.T.copy(), x2.T.copy())
    return (Xh[:3] / Xh[3]).T


def _scene(rng: np.random.Generator, inlier_ratio: float, n: int = 200):
    X = rng.uniform(-2, 2, (n, 3)) + [0, 0, 6]
    R = tf.so3_exp(rng.normal(scale=0.1, size=3))
    t = np.array([-1.0, 0.1, 0.2]) + rng.normal(scale=0.2, size=3)
    t /= np.linalg.norm(t)
    X2 = X @ R.T + t
    u1 = X @ K.T
    u1 = u1[:, :2] / u1[:, 2:] + rng.normal(scale=NOISE_PX, size=(n, 2))
    u2 = X2 @ K.T
    u2 = u2[:, :2] / u2[:, 2:] + rng.normal(scale=NOISE_PX, size=(n, 2))
    out = rng.random(n) >= inlier_ratio
    u2[out] = rng.uniform([0, 0], [W, H], (out.sum(), 2))
    return u1, u2, R, t


def ransac_section(rng: np.random.Generator, trials: int) -> str:
    rows = []
    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5  # OpenCV's pixel centre convention
    for ratio in (0.8, 0.5, 0.3, 0.2):
        scenes = [_scene(rng, ratio) for _ in range(trials)]
        for cap in (25, 100, 400, 1600):
            for backend in ("ours LO-MSAC", "cv2 USAC_MAGSAC", "cv2 RANSAC"):
                rot, tra, ok, secs, iters = [], [], 0, [], []
                for k, (u1, u2, R, t) in enumerate(scenes):
                    t0 = time.perf_counter()
                    if backend == "ours LO-MSAC":
                        cfg = TwoViewConfig(ransac=RansacConfig(max_iterations=cap, min_iterations=0, seed=k))
                        res = estimate_relative_pose(u1, u2, K, K, config=cfg)
                        R_e, t_e = res.R, res.t
                        iters.append(res.iterations)
                    else:
                        method = cv2.USAC_MAGSAC if "MAGSAC" in backend else cv2.RANSAC
                        E, mask = cv2.findEssentialMat(u1 - 0.5, u2 - 0.5, K_cv, method=method, prob=0.9999,
                                                       threshold=1.0, maxIters=cap)
                        if E is None or E.shape != (3, 3):
                            R_e, t_e = np.eye(3), np.zeros(3)
                        else:
                            _, R_e, t_e, _ = cv2.recoverPose(E, u1 - 0.5, u2 - 0.5, K_cv, mask=mask)
                            t_e = t_e.ravel()
                    secs.append(time.perf_counter() - t0)
                    er = float(rotation_error_deg(R_e, R))
                    et = float(translation_direction_error_deg(t_e, t))
                    et = 180.0 if not np.isfinite(et) else et
                    rot.append(er)
                    tra.append(et)
                    ok += er < 2.0 and et < 5.0
                rows.append([f"{ratio:g}", cap, backend, f"{ok}/{trials}", float(np.median(rot)),
                             float(np.median(tra)), float(np.mean(iters)) if iters else "-",
                             float(np.median(secs) * 1e3)])
    body = (
        f"200 matches, {NOISE_PX} px noise, f = {F_PX:g} px, threshold 1 px (Sampson), confidence 0.9999, "
        f"{trials} seeded scenes per inlier ratio (the same scenes for every backend and cap). Success: rotation "
        "error < 2 deg and translation-direction error < 5 deg. Ours stops early when the adaptive rule allows "
        "(mean iterations shown); OpenCV's iteration counts are not exposed. With 8 scenes per cell, a difference "
        "of one or two successes is within sampling noise. Ours is pure numpy (the 5-point solver alone is "
        "~1 ms per sample), OpenCV's is C++: compare the time columns as ratios.\n\n"
    )
    return body + md_table(
        ["inlier ratio", "max iterations", "estimator", "success", "median rot. err (deg)",
         "median t-dir err (deg)", "mean iterations", "median time (ms)"], rows
    )


def main() -> None:
    rng = np.random.default_rng(12345)
    trials = int(os.environ.get("BENCH_MVGEO_TRIALS", "8"))
    t0 = time.perf_counter()
    tri = triangulation_section(rng)
    ran = ransac_section(rng, trials)
    total = time.perf_counter() - t0
    body = (
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, shared with other "
        f"engineers' jobs while measured, so absolute times are noisy; compare ratios within one table. "
        f"Total run {total:.0f} s, peak RSS {peak_rss_mb():.0f} MiB.\n\n"
        "### Triangulation: error vs time over triangulation angle\n\n" + tri +
        "\n### Relative pose: RANSAC iterations vs success and error\n\n" + ran
    )
    path = write_fragment("mvgeo", "mvgeo: triangulation and two-view RANSAC", body)
    print(path)


if __name__ == "__main__":
    main()
