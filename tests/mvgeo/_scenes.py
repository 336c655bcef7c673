"""Synthetic two-view scenes shared by the mvgeo tests."""

from dataclasses import dataclass

import numpy as np

from mvgeo import transforms as tf

W, H = 640, 480


@dataclass
class TwoViewScene:
    K: np.ndarray
    R: np.ndarray  # cam2_from_cam1
    t: np.ndarray  # unit
    X1: np.ndarray  # points in camera 1
    u1: np.ndarray
    u2: np.ndarray
    inlier: np.ndarray


def project(K, X):
    u = X @ K.T
    return u[:, :2] / u[:, 2:]


def make_two_view(rng, *, n=150, noise_px=0.5, outlier_ratio=0.3, f=520.0, baseline=1.0, planar=False,
                  depth=6.0) -> TwoViewScene:
    """An object-in-front scene: points around depth 6, camera 2 moved sideways and rotated."""
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    X = rng.uniform(-2, 2, (n, 3)) + [0, 0, depth]
    if planar:
        X[:, 2] = depth + 0.3 * X[:, 0]
    R = tf.so3_exp(rng.normal(scale=0.1, size=3))
    t_dir = np.array([-1.0, 0.1, 0.2]) + rng.normal(scale=0.2, size=3)
    t = baseline * t_dir / np.linalg.norm(t_dir)
    X2 = X @ R.T + t
    u1 = project(K, X) + rng.normal(scale=noise_px, size=(n, 2))
    u2 = project(K, X2) + rng.normal(scale=noise_px, size=(n, 2))
    out = rng.random(n) < outlier_ratio
    u2[out] = rng.uniform([0, 0], [W, H], (out.sum(), 2))
    tn = t / np.linalg.norm(t) if baseline > 0 else t
    return TwoViewScene(K=K, R=R, t=tn, X1=X, u1=u1, u2=u2, inlier=~out)
