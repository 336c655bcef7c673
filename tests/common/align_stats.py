"""`AlignStats` for tests that stand in for `mvgeo.align.align_images` (only the fields a test sets matter)."""

from __future__ import annotations

import math

from mvgeo.align.stats import AlignStats, BundleStats


def bundle_stats(*, focal_log_std: float = math.nan, centre_std_ratio: list[float] | None = None) -> BundleStats:
    """A bundle-adjustment report with the two figures the pipeline reads; the others neutral."""
    return BundleStats(n_points=0, n_observations=0, reproj_rms_before_px=math.nan, reproj_rms_after_px=math.nan,
                       reproj_median_before_px=math.nan, reproj_median_after_px=math.nan,
                       focal_log_std=focal_log_std, solver="lm", centre_std_ratio=centre_std_ratio)


def align_stats(*, n_registered: int = 0, known_intrinsics: bool = False, bundle_adjustment: BundleStats | None = None,
                focal_px: dict[str, float] | None = None) -> AlignStats:
    """An `AlignStats` with these fields set and every other one empty."""
    return AlignStats(
        n_images=n_registered, n_registered=n_registered, input_size_wh=[0, 0], align_size_wh=[0, 0],
        pointmap_size_wh=[0, 0], n_pairs=0, n_pairs_ok=0, n_pairs_verified=0, failed_pairs=[],
        pairs_rejected_by_loops=[], unregistered=[], iterations=0, init_loss=math.nan, final_loss=math.nan,
        focal_px=dict(focal_px or {}), known_intrinsics=known_intrinsics, shared_focal=True,
        bundle_adjustment=bundle_adjustment, dense_stereo=None, focal_determined_by_pairs=True,
        sensitive_features=False, initial_poses="chain", candidates=[], pairs_dropped_as_inconsistent=[],
        pair_consistency_min=math.nan, pairs_inconsistent=[], n_points=0, mean_confidence=math.nan, timings_s={},
        config={})
