"""`mvgeo` command line: `align` (pose-free), `colmap` (pycolmap SfM), `compare` (pose metrics)."""

from __future__ import annotations

from mvgeo.common.threads import apply_thread_policy

# Before the imports below load torch: OpenMP reads OMP_WAIT_POLICY once, when it loads
# (mvgeo.common.threads.apply_thread_policy; docs/conventions.md, "Threads").
apply_thread_policy()

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from mvgeo.common.argtypes import int_range, nonneg_int, out_path, positive_int
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.errors import ConfigError, InputError
from mvgeo.common.output import OUT_HELP, OVERWRITE_HELP, prepare_output


def _pair_graph(text: str) -> str:
    """`--pairs`, checked by the parser (`PairGraphSpec.parse`)."""
    from mvgeo.align.graph import PairGraphSpec

    try:
        PairGraphSpec.parse(text)
    except ConfigError:
        raise argparse.ArgumentTypeError(f"expected complete, auto or window:K (K >= 1), got {text!r}") from None
    return text


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mvgeo", description=__doc__)
    add_common_args(p)
    sub = p.add_subparsers(dest="command", required=True)

    a = sub.add_parser("align", help="pose-free reconstruction: pairwise pointmaps + global alignment")
    a.add_argument("images_dir", type=Path)
    a.add_argument("--out", type=out_path, required=True, help=OUT_HELP)
    a.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    a.add_argument("--max-size", type=int_range(16), default=640, help="long side for matching (px); default 640")
    a.add_argument("--pointmap-size", type=int_range(8), default=128, help="long side of the dense pointmaps (px)")
    a.add_argument("--pairs", default="auto", type=_pair_graph,
                   help="complete | window:K | auto (complete up to 24 images)")
    a.add_argument("--shared-focal", action="store_true", help="one focal for all views")
    a.add_argument("--iters", type=nonneg_int, default=100, help="global alignment iterations (default 100)")
    a.add_argument("--align-stride", type=positive_int, default=None,
                   help="global alignment on every K-th pixel row/column of the pointmaps (default: "
                        "AlignConfig's, 8; 1 = all pixels)")
    a.add_argument("--ba", action=argparse.BooleanOptionalAction, default=True,
                   help="sparse bundle adjustment on the feature tracks after the alignment (default: on)")
    a.add_argument("--dense-stereo", action=argparse.BooleanOptionalAction, default=True,
                   help="recompute the cloud's depth maps by flow stereo with the final cameras at --max-size "
                        "(default: on; off: the global alignment's depth maps)")
    a.add_argument("--hole-fill", action=argparse.BooleanOptionalAction, default=True,
                   help="with the dense stereo, fill the wide holes of its depth maps (textureless surfaces) by "
                        "harmonic interpolation of the inverse depth, at low confidence (default: on)")
    a.add_argument("--points", type=positive_int, default=200_000, help="point budget of points.ply")
    a.add_argument("--downsample", choices=["pixel", "voxel"], default="pixel",
                   help="thinning to --points: most confident point per pixel cell of each view (default) "
                        "or per voxel")
    a.add_argument("--intrinsics", type=Path, help="COLMAP cameras.txt or mrcal .cameramodel of these images")
    a.add_argument("--cloud-images", type=Path, metavar="DIR",
                   help="a folder with the same views under the same file names (e.g. denoised versions of noisy "
                        "photos): the dense cloud's stereo and colours come from them, the poses from IMAGES_DIR")
    a.add_argument("--exif-focal", action=argparse.BooleanOptionalAction, default=True,
                   help="without --intrinsics, start at the photos' EXIF 35 mm-equivalent focal length when they all "
                        "carry the same one (default: on; align.json 'focal_prior')")
    a.add_argument("--allow-partial", action="store_true",
                   help="if some images cannot be connected, register the largest connected group and list "
                        "the others in align.json 'unregistered' (default: fail naming them). The group is checked "
                        "only by its own pairs: on weak sets (noisy, 20-40 deg apart) 2 of 10 draws came back "
                        "with relative rotations 11 deg off, and the noisy temple ring's 16 views up to 21 deg off "
                        "(docs/bench/real_partial_draws.md, real_subsets.md)")
    a.add_argument("--initial-poses", choices=["auto", "chain", "averaged"], default="auto",
                   help="how the poses are initialised: DUSt3R's chaining of the pairs' pointmaps, rotation "
                        "averaging then positions from the tracks (GLOMAP's approach), or 'auto' (default: chaining "
                        "first unless the chained start contradicts most pairs' relative rotations; "
                        "mvgeo.align.init.choose_start)")
    a.add_argument("--principal-point", choices=["auto", "centre"], default="auto",
                   help="without --intrinsics: 'auto' (default) estimates the principal point for the accepted "
                        "result and keeps it where the views determine it (views around an object do, close views "
                        "do not; align.json principal_point says which and why); 'centre' keeps the image centre "
                        "(COLMAP's default)")
    add_common_args(a)

    c = sub.add_parser("colmap", help="pycolmap SfM (CPU SIFT, exhaustive matching) into the same layout")
    c.add_argument("images_dir", type=Path)
    c.add_argument("--out", type=out_path, required=True, help=OUT_HELP)
    c.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    c.add_argument("--global", dest="global_mapper", action="store_true", help="global instead of incremental")
    add_common_args(c)

    m = sub.add_parser("compare", help="pose metrics of EST against REF after Sim(3) alignment (by image name)")
    m.add_argument("est", type=Path, help="estimated sparse model folder (sparse/0)")
    m.add_argument("ref", type=Path, help="reference sparse model folder")
    m.add_argument("--json", action="store_true", help="print JSON")
    add_common_args(m)
    return p


def _align(args: argparse.Namespace) -> int:
    plan = prepare_output(args.out, command="mvgeo align", inputs=[args.images_dir, args.intrinsics,
                                                                   args.cloud_images], overwrite=args.overwrite)
    from mvgeo.align.api import AlignConfig, align_images, write_align_result
    from mvgeo.align.classical_pairs import ClassicalPairConfig
    from mvgeo.align.dense_stereo import DenseStereoConfig
    from mvgeo.align.global_align import GlobalAlignConfig
    from mvgeo.align.graph import PairGraphSpec
    from mvgeo.align.hole_fill import HoleFillConfig
    from mvgeo.align.intrinsics import read_intrinsics
    from mvgeo.common.imageio import list_images, read_image, upright_size

    paths = list_images(args.images_dir)
    if len(paths) < 2:
        raise InputError(f"need at least 2 images, found {len(paths)}", path=args.images_dir,
                         fix="add more views of the scene")
    intr = read_intrinsics(args.intrinsics) if args.intrinsics else None
    if intr is not None:  # checked here too, where the file is known, before any image is matched
        w, h = upright_size(paths[0]) or read_image(paths[0]).shape[1::-1]  # the header, else the pixels
        if (intr.width, intr.height) != (w, h):
            raise InputError(f"the calibration is for {intr.width}x{intr.height} images, the images are {w}x{h} "
                             f"({paths[0].name})", path=args.intrinsics,
                             fix="pass the calibration of these images at their size")
    cloud = None
    if args.cloud_images is not None:
        if not args.cloud_images.is_dir():
            raise InputError("--cloud-images is not a folder" if args.cloud_images.exists() else
                             "--cloud-images does not exist", path=args.cloud_images,
                             fix="pass the folder of the same views (e.g. the denoised photos), file names as in "
                                 "the images folder")
        cloud = [args.cloud_images / p.name for p in paths]
        missing = [c.name for c in cloud if not c.is_file()]
        if missing:
            raise InputError(f"--cloud-images lacks {missing}", path=args.cloud_images,
                             fix="give it the same views under the same file names as the images folder")
    cfg = AlignConfig(max_size_px=args.max_size, pairs=PairGraphSpec.parse(args.pairs),
                      pairwise=ClassicalPairConfig(pointmap_size_px=args.pointmap_size),
                      align=GlobalAlignConfig(iters=args.iters, shared_focal=args.shared_focal,
                                              pixel_stride=args.align_stride or AlignConfig().align.pixel_stride),
                      points_budget=args.points, bundle_adjust=args.ba, allow_partial=args.allow_partial,
                      downsample=args.downsample, dense_stereo=DenseStereoConfig(enabled=args.dense_stereo),
                      hole_fill=HoleFillConfig(enabled=args.hole_fill), initial_poses=args.initial_poses,
                      exif_focal=args.exif_focal, principal_point=args.principal_point)
    result = align_images(paths, cfg, intrinsics=intr, cloud_images=cloud)
    write_align_result(plan, result)
    s = result.stats
    if s.unregistered:
        print(f"warning: {len(s.unregistered)} images not registered: {[u.name for u in s.unregistered]}",
              file=sys.stderr)
    prior = f", focal prior {s.focal_prior.focal_35mm:g} mm ({s.focal_prior.source})" if s.focal_prior else ""
    pp = s.principal_point
    if pp is not None and pp.kept:
        prior += f", principal point {pp.offset_px[0]:+.1f}, {pp.offset_px[1]:+.1f} px off the centre (determined)"
    moved = [v.name for v in s.views_located_by_points if v.outcome == "re-posed"]
    if moved:
        print(f"note: {moved} re-posed where PnP on the other views' points puts them (align.json "
              "views_located_by_points)", file=sys.stderr)
    ba = s.bundle_adjustment
    fit = "" if ba is None else f", reprojection RMS {ba.reproj_rms_after_px:.3g} px over {ba.n_points} tracks"
    focals = sorted(s.focal_px.values())
    if focals and not s.known_intrinsics:
        how = "from the pairs" if s.focal_determined_by_pairs else "not determined by the pairs"
        std = f", log-std {ba.focal_log_std:.3f}" if ba is not None else ""
        fit += f", focal {focals[len(focals) // 2]:.1f} px ({how}{std})"
    ga = f", alignment loss {s.init_loss:.4g} -> {s.final_loss:.4g}" if s.iterations else ""  # where it ran
    print(f"aligned {s.n_registered}/{s.n_images} images ({s.n_pairs_ok}/{s.n_pairs} pairs, {s.initial_poses} "
          f"start, {len(s.candidates)} candidate(s){prior}), {s.n_points} points{ga}{fit}, "
          f"{s.timings_s['total']:.1f} s -> {args.out}")
    return 0


def _colmap(args: argparse.Namespace) -> int:
    plan = prepare_output(args.out, command="mvgeo colmap", inputs=[args.images_dir], overwrite=args.overwrite)
    from mvgeo.align.colmap_sfm import ColmapConfig, run_colmap, write_colmap_result

    res = run_colmap(args.images_dir, replace(ColmapConfig(), mapper="global" if args.global_mapper else "incremental"))
    write_colmap_result(plan, res)
    s = res.stats
    print(f"COLMAP ({s.mapper}): registered {s.n_registered}/{s.n_images} images, {s.n_points} points, "
          f"{s.timings_s['total']:.1f} s -> {args.out}")
    return 0


def _compare(args: argparse.Namespace) -> int:
    from mvgeo.metrics import compare_poses
    from mvgeo.sparse_model import read_sparse_model

    est = read_sparse_model(args.est)
    ref = read_sparse_model(args.ref)
    common = set(est.names) & set(ref.names)
    if len(common) == 1:
        raise InputError(f"the two models have one image in common ({sorted(common)[0]}): relative poses need two",
                         path=args.est, fix="compare models that share at least two images (the poses are matched "
                                            "by image file name)")
    if not common:
        raise InputError(f"no image names in common between the two models (EST has {len(est.names)} "
                         f"images, e.g. {est.names[:2]}; REF has {len(ref.names)}, e.g. {ref.names[:2]}): "
                         "there is nothing to compare", path=args.est,
                         fix="compare models of the same images; the poses are matched by image file name")
    m = compare_poses(est.cam_from_world_by_name(), ref.cam_from_world_by_name())
    out = {"n_ref": m.n_ref, "n_registered": m.n_registered, **m.summary()}
    if args.json:  # a figure the views do not determine (NaN: the ATE of 2 views) is null, as JSON allows
        print(json.dumps({k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in out.items()},
                         indent=2, allow_nan=False))
    else:
        for k, v in out.items():
            print(f"{k:>24}: {v:.4g}" if isinstance(v, float) else f"{k:>24}: {v}")
    return 0


def _main(args: argparse.Namespace) -> int:
    return {"align": _align, "colmap": _colmap, "compare": _compare}[args.command](args)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `mvgeo` console script."""
    return run_cli(_main, _parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
