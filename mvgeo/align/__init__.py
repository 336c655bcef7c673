"""Pose-free alignment of a few photos (`mvgeo align`), DUSt3R-style, with a classical pair model.

Python API (what `mvgeo align` runs)::

    from mvgeo.align import AlignConfig, align_images, write_align_result
    result = align_images(sorted(Path("scene/images").glob("*.png")), AlignConfig())
    result.sparse_model        # SparseModel: PINHOLE cameras at the input size, cam_from_world per image
    result.points_xyz, result.points_rgb, result.points_conf   # dense cloud (P, 3), (P, 3) uint8, (P,)
    result.stats               # timings, losses, focals, failed pairs, bundle-adjustment report
    write_align_result("out", result)  # out/sparse/0/*.bin, out/points.ply, out/align.json (atomic)

Pipeline and modules:

- `pairs`: `PairPrediction` (DUSt3R's pairwise output format) and the
  `PointmapModel` protocol: `predict_pairs(images, pairs) -> (predictions, failures)`.
  A learned DUSt3R/MASt3R wrapper can be passed as `align_images(..., model=...)`.
- `classical_pairs`: the default, weight-free model (SIFT with RootSIFT
  mutual-ratio matching in one BLAS product, shared-focal relative pose from
  `mvgeo.twoview` with OpenCV's USAC_MAGSAC, edge-aware + DIS dense flow with a
  forward-backward check, `mvgeo.triangulate`, confidences >= 1). Dense
  pointmaps for each view's 4 strongest pairs (+ a spanning tree); the sparse
  matches of every verified pair go to the bundle adjustment.
- `graph`: complete / window:K pair graphs, connectivity, maximum spanning tree.
- `global_align`: DUSt3R's global alignment in torch (per-view log-depth, pose,
  log-focal; per-pair similarity; sum of log(conf)-weighted Euclidean
  residuals; pinned geometric-mean pair scale; MST + Procrustes init; Adam + cosine).
- `bundle`, `bundle_lm`: sparse bundle adjustment on multi-view feature tracks
  (Levenberg-Marquardt with the Schur complement, analytic Jacobian, Huber
  loss, shared or per-view focal; scipy `least_squares` kept as the reference).
  This step sets the final pose accuracy. When it moves the shared focal by more
  than 10 % from the one the pairs were computed with, the pairs are computed
  again with its focal (same matches) and the alignment runs once more
  (`AlignConfig.refocus_min_change`; two-view focals fail for narrow fields of view).
- `checks`: every verified pair's matches must be explained by the final
  geometry; otherwise the inconsistent pairs are dropped and the problem
  solved once more, and a result that still contradicts the evidence (or whose
  focal length nothing determines) fails with a specific message.
- `dense_stereo`: once the cameras are final, the output cloud's depth maps are
  recomputed by flow stereo per pair with those cameras at `max_size_px`, fused
  per view (the pairwise pointmaps carry their own pair poses' errors).
- `hole_fill`: the wide holes of those depth maps (textureless surfaces, where
  flow stereo finds nothing) get the harmonic interpolation of the inverse depth
  around them, at low confidence.
- `scene`: co-visibility pruning, the multi-view consistency check, and
  confidence-aware thinning to the point budget (per pixel cell of each view by
  default, or per voxel).
- `intrinsics`: known calibration (COLMAP cameras.txt, mrcal .cameramodel) and undistortion.
- `colmap_sfm`: the pycolmap SfM reference (`mvgeo colmap`).

Resolutions: matching and the final dense stereo at `max_size_px` (512) on the
long side; pairwise pointmaps and the optimised depth maps at
`pairwise.pointmap_size_px` (128), the global alignment on every 4th pixel
row/column (100 iterations); cameras are written at the input images'
resolution (intrinsics scaled).
"""

from mvgeo.align.api import PREVIEW, AlignConfig, AlignResult, align_images, write_align_result
from mvgeo.align.pairs import PairFailure, PairPrediction, PointmapModel

__all__ = ["PREVIEW", "AlignConfig", "AlignResult", "PairFailure", "PairPrediction", "PointmapModel",
           "align_images", "write_align_result"]
