"""`splat train DATA_DIR --out OUT` and `splat render MODEL_DIR --cameras SPARSE_DIR --out DIR`.

`splat export MODEL --format ply|splat|spz|html --out PATH` (web formats, offline viewer; `splat.export`,
`splat.viewer`) and `splat view MODEL` (a viser server on 127.0.0.1).

Thin: parse, call `splat.train` / `splat.render`, write files, report.
Output of `train` (written atomically):

    OUT/point_cloud.ply     3DGS PLY of the trained Gaussians
    OUT/sparse/0/           the training cameras with optimised poses (COLMAP text)
    OUT/train_curve.png     loss and PSNR against iteration
    OUT/history.json        the curve's numbers; OUT/report.json: config, timings, counts
"""

from __future__ import annotations

from mvgeo.common.threads import apply_thread_policy

# Before the imports below load torch: OpenMP reads OMP_WAIT_POLICY once, when it loads
# (mvgeo.common.threads.apply_thread_policy; docs/conventions.md, "Threads").
apply_thread_policy()

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from mvgeo.common.argtypes import int_range, out_path, positive_int, seed
from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.device import DEVICE_HELP, resolve_device
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import check_distinct_stems, write_image
from mvgeo.common.output import OUT_HELP, OVERWRITE_HELP, prepare_output, prepare_output_file, write_output_file
from mvgeo.common.timing import StageTimer
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model
from splat.dataset import load_views, points_from_depth, read_point_cloud_ply
from splat.ply import read_gaussian_ply, write_gaussian_ply
from splat.render import render_views
from splat.train import TRAIN_PRESETS, preset, train_gaussians


def _plot_curve(path: Path, history) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].plot(history.iteration, history.loss)
    ax[0].set(xlabel="iteration", ylabel="loss (0.8 L1 + 0.2 D-SSIM)", yscale="log")
    ax[1].plot(history.iteration, history.psnr_db)
    ax[1].set(xlabel="iteration", ylabel="train-view PSNR (dB)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _init_points(args, data_dir: Path, views):
    if args.init is None:
        if len(views.sparse.points_xyz) >= 2:
            return views.sparse.points_xyz, views.sparse.points_rgb
        raise InputError("the sparse model has no 3D points to initialise from", path=data_dir / "sparse",
                         fix="pass --init POINTS.ply (e.g. from `mvgeo align`), or --init depth for a "
                             "data-synth folder with depth/")
    if args.init == "depth":
        return points_from_depth(data_dir, views, stride_px=args.depth_stride)
    xyz, rgb = read_point_cloud_ply(args.init)
    if len(xyz) < 2:
        raise InputError(f"--init holds {len(xyz)} point(s); the splat needs at least 2 to start from",
                         path=args.init, fix="pass a point cloud with points (e.g. `mvgeo align`'s points.ply), or "
                                             "leave --init out to start from sparse/0's points")
    bad = ~np.isfinite(np.asarray(xyz, np.float64)).all(axis=1)
    if bad.any():
        raise InputError(f"--init: {int(bad.sum())} of its {len(xyz)} points are NaN or infinite (the first: "
                         f"vertex {int(np.flatnonzero(bad)[0])})", path=args.init,
                         fix="remove those vertices, or write the cloud again")
    return xyz, rgb


def _train(args) -> int:
    data_dir = Path(args.data_dir)
    device = resolve_device(args.device)
    init_file = None if args.init in (None, "depth") else args.init
    plan = prepare_output(args.out, command="splat train", inputs=[data_dir, init_file], overwrite=args.overwrite)
    timer = StageTimer()
    overrides = {"optimize_poses": args.optimize_poses, "seed": args.seed}
    if args.iters is not None:
        overrides["iters"] = args.iters
    config = preset(args.preset, **overrides)
    with timer.stage("load"):
        views = load_views(data_dir, split="train")
        xyz, rgb = _init_points(args, data_dir, views)
    result = train_gaussians(views.images, views.cameras, views.cam_from_world, xyz, rgb, config,
                             device=device)
    # Stages only: the "optimize/..." parts are already inside "optimize" and would count twice in the total.
    timer.seconds.update({f"train.{k}": v for k, v in result.timings_s.items() if k != "total" and "/" not in k})
    with timer.stage("write"), atomic_output_dir(plan) as tmp:
        write_gaussian_ply(tmp / "point_cloud.ply", result.model)
        ids = {name: views.sparse.image(name).camera_id for name in views.names}
        images = [PosedImage(n, ids[n], p) for n, p in zip(views.names, result.cam_from_world_optimized, strict=True)]
        cams = {cid: views.sparse.cameras[cid] for cid in set(ids.values())}
        (tmp / "sparse" / "0").mkdir(parents=True)
        write_sparse_model(tmp / "sparse" / "0", SparseModel(cameras=cams, images=images), binary=False)
        _plot_curve(tmp / "train_curve.png", result.history)
        (tmp / "history.json").write_text(json.dumps(dataclasses.asdict(result.history)))
        report = {"data_dir": str(data_dir), "train_views": views.names, "num_init_points": int(len(xyz)),
                  "num_gaussians": result.model.num_gaussians, "preset": args.preset,
                  "config": json.loads(json.dumps(dataclasses.asdict(config), default=str)),
                  "timings_s": timer.as_dict(),
                  "train_optimize_parts_s": {k: v for k, v in result.timings_s.items() if "/" in k}}
        (tmp / "report.json").write_text(json.dumps(report, indent=2))
    print(f"trained {result.model.num_gaussians} Gaussians on {len(views.names)} views in "
          f"{result.timings_s['total']:.1f} s -> {args.out}")
    return 0


def _render(args) -> int:
    model_dir = Path(args.model_dir)
    device = resolve_device(args.device)
    plan = prepare_output(args.out, command="splat render", inputs=[model_dir, args.cameras],
                          overwrite=args.overwrite)
    ply = model_dir / "point_cloud.ply" if model_dir.is_dir() else model_dir
    sparse = read_sparse_model(Path(args.cameras))
    if not sparse.images:
        raise InputError("the camera model has no images to render", path=args.cameras)
    check_distinct_stems(sparse.names, path=args.cameras)  # one output file per view
    for camera_id in sorted({im.camera_id for im in sparse.images}):
        if (problem := sparse.cameras[camera_id].pinhole_problem()) is not None:  # before anything is rendered
            raise InputError(f"camera {camera_id} cannot be rendered: {problem}", path=args.cameras,
                             fix="undistort the images and cameras first (e.g. COLMAP image_undistorter)")
    model = read_gaussian_ply(ply, device=device)
    cams = [sparse.camera_of(n) for n in sparse.names]
    poses = np.stack([im.cam_from_world for im in sparse.images])
    with torch.no_grad():
        imgs = render_views(model, cams, poses)
    with atomic_output_dir(plan) as tmp:
        for name, img in zip(sparse.names, imgs, strict=True):
            write_image(tmp / (Path(name).stem + ".png"), img)
    print(f"rendered {len(imgs)} views -> {args.out}")
    return 0


def _model_and_cameras(args):
    """(model, sparse model or None) for `export`/`view`: MODEL is a folder with point_cloud.ply (and
    sparse/0/, used as the cameras unless --cameras is given) or a 3DGS PLY file."""
    model_path = Path(args.model)
    ply = model_path / "point_cloud.ply" if model_path.is_dir() else model_path
    cameras = args.cameras
    if cameras is None and model_path.is_dir() and (model_path / "sparse" / "0").is_dir():
        cameras = model_path / "sparse" / "0"
    sparse = read_sparse_model(Path(cameras)) if cameras is not None else None
    return read_gaussian_ply(ply), sparse


def _export(args) -> int:
    from splat.export import EXPORT_FORMATS, export_model
    from splat.viewer import export_html

    suffix = Path(args.out).suffix.lstrip(".").lower()
    fmt = args.format or suffix
    if args.format and suffix in EXPORT_FORMATS and suffix != args.format:  # .splat bytes in a .ply file
        what = "a folder with index.html" if args.format == "html" else f"a .{args.format} file"
        raise InputError(f"--format {args.format} writes {what}, --out names a .{suffix} file", path=args.out,
                         fix=f"name --out NAME.{args.format}" + (" (or a folder)" if args.format == "html" else "") +
                             ", or leave --format out")
    if fmt not in EXPORT_FORMATS:
        raise InputError(f"cannot tell the format from --out '{args.out}'",
                         fix=f"pass --format ({' | '.join(EXPORT_FORMATS)})")
    inputs = [args.model, args.cameras]
    if fmt == "html":
        plan = prepare_output(args.out, command="splat export", inputs=inputs, overwrite=args.overwrite)
        model, sparse = _model_and_cameras(args)
        index = export_html(model, plan, sparse=sparse)
        print(f"viewer of {model.num_gaussians} Gaussians -> {index} (open it in a browser; no network needed)")
        return 0
    out = prepare_output_file(args.out, command="splat export", inputs=inputs, overwrite=args.overwrite,
                              example_name=f"scene.{fmt}")
    model, _ = _model_and_cameras(args)
    write_output_file(out, "splat export", lambda tmp: export_model(model, fmt, tmp))
    print(f"{model.num_gaussians} Gaussians -> {args.out} ({fmt}, {out.stat().st_size} bytes)")
    return 0


def _view(args) -> int:
    from splat.viewer import check_listen_address, serve

    check_listen_address(args.host, args.port)  # before the model loads
    model, sparse = _model_and_cameras(args)
    serve(model, sparse, host=args.host, port=args.port)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="splat", description="Gaussian splatting: train and render (CPU or CUDA).")
    add_common_args(parser)
    sub = parser.add_subparsers(dest="command", required=True)
    tr = sub.add_parser("train", help="train Gaussians on DATA_DIR (images/ + sparse/0/, split.json train views)")
    tr.add_argument("data_dir", help="folder with images/ and sparse/0/ (and optionally split.json, depth/)")
    tr.add_argument("--out", type=out_path, required=True, help=OUT_HELP)
    tr.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    tr.add_argument("--iters", type=positive_int, default=None, help="iterations (default: the preset's, 1000)")
    tr.add_argument("--optimize-poses", action=argparse.BooleanOptionalAction, default=False,
                    help="learn per-view pose corrections (InstantSplat); off for ground-truth poses")
    tr.add_argument("--init", default=None,
                    help="initial points: a point-cloud PLY, or 'depth' to back-project DATA_DIR/depth/*.npy; "
                         "default: the sparse model's points")
    tr.add_argument("--depth-stride", type=positive_int, default=4, help="pixel stride for --init depth")
    tr.add_argument("--preset", default="instantsplat", choices=sorted(TRAIN_PRESETS))
    tr.add_argument("--seed", type=seed, default=0)
    tr.add_argument("--device", default="cpu", help=DEVICE_HELP)
    tr.set_defaults(func=_train)
    rd = sub.add_parser("render", help="render a trained model at the cameras of a COLMAP model")
    rd.add_argument("model_dir", help="`splat train` output folder (or a 3DGS point_cloud.ply)")
    rd.add_argument("--cameras", required=True, help="COLMAP model folder (cameras + images)")
    rd.add_argument("--out", type=out_path, required=True, help="folder of PNGs; " + OUT_HELP)
    rd.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    rd.add_argument("--device", default="cpu", help=DEVICE_HELP)
    rd.set_defaults(func=_render)
    ex = sub.add_parser("export", help="write a model as .ply, .splat, .spz, or an offline browser viewer (html)")
    ex.add_argument("model", help="`splat train` output folder (or a 3DGS point_cloud.ply)")
    ex.add_argument("--format", choices=("ply", "splat", "spz", "html"), default=None,
                    help="default: from --out's suffix; html writes a folder with index.html")
    ex.add_argument("--out", type=out_path, required=True, help="output file (a folder for html)")
    ex.add_argument("--overwrite", action="store_true",
                    help="replace an existing --out written by this command and unchanged since (nothing else is "
                         "ever replaced)")
    ex.add_argument("--cameras", default=None,
                    help="html only: COLMAP model whose cameras are drawn (default: MODEL/sparse/0 if present)")
    ex.set_defaults(func=_export)
    vw = sub.add_parser("view", help="serve a model in the browser with viser (http://127.0.0.1:PORT)")
    vw.add_argument("model", help="`splat train` output folder (or a 3DGS point_cloud.ply)")
    vw.add_argument("--cameras", default=None, help="COLMAP model whose cameras are drawn (default: MODEL/sparse/0)")
    vw.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")
    vw.add_argument("--port", type=int_range(0, 65535), default=8080, help="TCP port, 0-65535 (default 8080)")
    vw.set_defaults(func=_view)
    return parser


def main(argv=None) -> int:
    return run_cli(lambda args: args.func(args), build_parser(), argv)
