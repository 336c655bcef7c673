"""OpenCV's USAC_MAGSAC can return a model that does not explain the consensus set it reports; the
`opencv` backend of `mvgeo.twoview` refits that set (`_USAC_MIN_EXPLAINED`).

The draws: points on a small object (3 cm spread, 0.6 m away) seen by two cameras of focal 1520 px (the
temple ring's calibration at 640 x 480) turned 10-40 deg about it, 0.3 px noise and uniform outliers: a
narrow, ill-conditioned view of the object, where the rotation is only known to about a degree. On OpenCV
5.0.0, draws 61 and 156 give a MAGSAC essential matrix that explains 10 of 46 and 8 of 69 reported inliers
at the 1 px threshold (on denoised temple photos: 0 of 58; on the same draws with the points spread over
20 cm, none of 1000). Without the refit both fail when the pose is not refined ("only 10 / 8 inliers");
with `TwoViewConfig.refine` the LM refinement from those 8-10 points happens to recover them, which it
cannot when the model explains fewer than the 6 points it needs (the temple pair).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvgeo.common.deps import cv2
from mvgeo.epipolar import fundamental_from_essential, sampson_distance
from mvgeo.twoview import (
    TwoViewConfig,
    _to_norm,
    estimate_fundamental,
    estimate_relative_pose,
    project_to_essential,
)

F_PX = 1520.0
K = np.array([[F_PX, 0.0, 320.0], [0.0, F_PX, 240.0], [0.0, 0.0, 1.0]])
CONFIG = TwoViewConfig(backend="opencv", min_inliers=12, refine=True)
UNREFINED = TwoViewConfig(backend="opencv", min_inliers=12, refine=False)


def _draw(seed: int):
    """(u1, u2, n_inliers, R_2_from_1): the first n_inliers matches are true (0.3 px noise), the rest random."""
    rng = np.random.default_rng(seed)
    n_in, n_out = int(rng.integers(20, 80)), int(rng.integers(5, 40))
    X = rng.normal(0.0, 0.03, (n_in, 3)) + [0.0, 0.0, 0.6]
    R = Rotation.from_rotvec([0.0, np.radians(rng.uniform(10, 40)), 0.0]).as_matrix()
    c = np.array([0.0, 0.0, 0.6])
    t = c - R @ c  # turned about the object
    x1 = X @ K.T
    x2 = (X @ R.T + t) @ K.T
    u1 = x1[:, :2] / x1[:, 2:] + rng.normal(0.0, 0.3, (n_in, 2))
    u2 = x2[:, :2] / x2[:, 2:] + rng.normal(0.0, 0.3, (n_in, 2))
    o1 = rng.uniform([0, 0], [640, 480], (n_out, 2))
    o2 = rng.uniform([0, 0], [640, 480], (n_out, 2))
    return np.vstack([u1, o1]), np.vstack([u2, o2]), n_in, R


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1.0) / 2.0, -1.0, 1.0))))


@pytest.mark.parametrize("refine", [False, True])
@pytest.mark.parametrize("seed", [61, 156])
def test_relative_pose_survives_an_inconsistent_usac_model(seed, refine):
    u1, u2, n_in, R = _draw(seed)
    # What OpenCV itself returns on this draw (reported, not asserted: another OpenCV may not do it).
    E, mask = cv2.findEssentialMat(_to_norm(u1, K), _to_norm(u2, K), np.eye(3), method=cv2.USAC_MAGSAC,
                                   prob=CONFIG.ransac.confidence, threshold=1.0 / F_PX,
                                   maxIters=CONFIG.ransac.max_iterations)
    raw = int((sampson_distance(fundamental_from_essential(project_to_essential(E[:3]), K, K), u1, u2) < 1.0).sum())
    print(f"draw {seed}: OpenCV reports {int(mask.sum())} inliers, its model explains {raw}")
    res = estimate_relative_pose(u1, u2, K, K, config=CONFIG if refine else UNREFINED)
    assert res.success, res.reason
    # 0.3 px noise at a 1 px threshold keeps nearly every true match; a few outliers fall in the band.
    assert res.inlier_mask[:n_in].sum() >= 0.9 * n_in
    assert res.inlier_mask[n_in:].sum() <= 2
    # The model fits the true matches to their noise (RMS Sampson distance 0.3 px expected; 2x allowed) ...
    d = sampson_distance(fundamental_from_essential(res.E, K, K), u1[:n_in], u2[:n_in])
    assert np.sqrt(np.mean(d**2)) < 0.6
    if refine:  # ... and the rotation is as close as this narrow geometry allows (measured 0.2 and 1.2 deg;
        # the median over 400 such draws is 0.77 deg, the unrefined 5-point model's 2.8 and 9.5 deg here)
        assert _angle_deg(res.R, R) < 2.0


@pytest.mark.parametrize("seed", [61, 156])
def test_fundamental_explains_the_true_matches(seed):
    """`estimate_fundamental` (opencv backend) on the same draws: the F returned explains the true matches."""
    u1, u2, n_in, _ = _draw(seed)
    F, inliers, _ = estimate_fundamental(u1, u2, config=CONFIG)
    assert F is not None
    assert inliers[:n_in].sum() >= 0.8 * n_in
    # The mask is the returned F's own (OpenCV's USAC mask can disagree with its model, the bug this file is
    # about): F itself must explain the true matches at the threshold, and the mask be the matches it explains.
    d = sampson_distance(F, u1, u2)
    thr = CONFIG.ransac.threshold_px
    assert (d[:n_in] < thr).mean() >= 0.8
    assert (d[n_in:] < thr).sum() <= 2  # random outliers falling in the 1 px band by chance
    np.testing.assert_array_equal(inliers, d < thr)
