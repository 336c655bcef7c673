"""Pose-free alignment of a few photos (`mvgeo align`): pairwise pointmaps, DUSt3R global alignment, bundle adjustment.

Python API (what `mvgeo align` runs)::

    from mvgeo.align import AlignConfig, align_images, write_align_result
    result = align_images(sorted(Path("scene/images").glob("*.png")), AlignConfig())
    result.sparse_model        # SparseModel: PINHOLE cameras at the input size, cam_from_world per image
    result.points_xyz, result.points_rgb, result.points_conf   # dense cloud (P, 3), (P, 3) uint8, (P,)
    result.stats               # AlignStats: what ran, the candidates, the bundle adjustment, timings
    write_align_result("out", result)  # out/sparse/0/*.bin, out/points.ply, out/align.json (atomic)

Stages (`api.align_images` is the orchestrator), each a module with a typed result:

1. `inputs`: the images checked, undistorted with known intrinsics, downscaled once (`AlignInputs`).
2. `features` + `classical_pairs`: SIFT and putative matches, once per image and pair (`MatchSet`); each
   pair's relative pose at one shared focal (the photos' common EXIF 35 mm-equivalent focal,
   `intrinsics.exif_focal_prior`; else the one at least three pairs' focals agree on, `pair_focal.consensus_focal`;
   else COLMAP's prior; re-estimated by `policy` when the adjustment moves it) and dense pointmaps (`PairSet`,
   defined in `pairs` with the `PointmapModel` protocol a learned DUSt3R/MASt3R wrapper can implement;
   `dense_pairs` holds the flows and the triangulated pointmaps).
3. `solve`: the pair graph (loop check `loops`, connectivity `graph`), then one candidate: initial poses
   (`init`: DUSt3R's chaining, with the pairs' own relative poses in `pose_chain`, or rotation averaging
   `rotation_averaging` then positions), DUSt3R's global alignment (`global_align`, objective in
   `alignment_objective`, pointmap rays and Procrustes in `pointmap_geometry`), bundle adjustment on every
   verified pair's tracks (`bundle`, `bundle_lm`), and a `verdict` (the pair-consistency tests in `checks`)
   with typed reasons naming the views (raised as
   `mvgeo.common.errors.AlignmentRefusedError`: kind, views, message and fix). Views the verdict would
   cut off (every link contradicted) are first located by PnP on points the main group triangulates from
   guided matches (`locate`, `guided`).
4. `policy`: which candidates are solved (focal re-estimation, re-posing views PnP places elsewhere
   (`solve.relocate`), pruning of contradicted pairs, the second start) and the one rule that chooses;
   then `principal`: the accepted result's principal point, kept where the views determine it.
5. `cloud`: depth maps recomputed by flow stereo with the final cameras (`dense_stereo`, `hole_fill`;
   optionally from other pixels of the same views, `align_images`' `cloud_images`), co-visibility pruning
   and thinning (`scene`). With `AlignConfig.candidate_align_iters` set, the candidates run fewer global
   alignment iterations and it runs in full once, for the chosen candidate's cloud where the cloud uses its
   depth maps (`solve.cloud_alignment`).
6. `stats` (`AlignStats`, align.json) and `writer`.

Also: `intrinsics` (known calibration, undistortion, the EXIF focal prior), `colmap_sfm` (the pycolmap
reference, `mvgeo colmap`), `translation_averaging` (global positioning of the cameras from the tracks;
its LUD start in `lud`).
Options: `config.AlignConfig`.
"""

import importlib

#: Public name -> the module that defines it. Imported on first use (PEP 562), so that `mvgeo.align.stats`
#: or `mvgeo.align.pairs` can be imported without loading torch, OpenCV and pycolmap.
_EXPORTS = {"PREVIEW": "config", "AlignConfig": "config", "AlignResult": "result", "AlignStats": "stats",
            "FocalPrior": "intrinsics", "PairFailure": "pairs", "PairGeometry": "pairs", "PairPrediction": "pairs",
            "PairSet": "pairs", "PointmapModel": "pairs", "align_images": "api", "write_align_result": "writer"}

__all__ = ["PREVIEW", "AlignConfig", "AlignResult", "AlignStats", "FocalPrior", "PairFailure", "PairGeometry",
           "PairPrediction", "PairSet", "PointmapModel", "align_images", "write_align_result"]


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"mvgeo.align.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'mvgeo.align' has no attribute {name!r}")
