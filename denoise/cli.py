"""`denoise` command line: `denoise n2v IMAGES_DIR --out OUT` and `denoise select SPARSE_DIR --images DIR`."""

from __future__ import annotations

from mvgeo.common.threads import apply_thread_policy

# Before the imports below load torch: OpenMP reads OMP_WAIT_POLICY once, when it loads
# (mvgeo.common.threads.apply_thread_policy; docs/conventions.md, "Threads").
apply_thread_policy()

import argparse
import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from denoise.grouped_wiener import GroupedWienerConfig
from denoise.inference import NOISE_MODELS
from denoise.model import save_checkpoint
from denoise.n2v import METHODS, N2V_PRESETS, n2v_preset
from denoise.pixel_shuffle import MAX_STRIDE, shuffled, stride_for, unshuffled
from denoise.self_supervised import choose_objective, denoise_with_method, train_with_method
from denoise.view_selection import select_views
from denoise.wiener import WienerConfig
from mvgeo.common.argtypes import int_range, nonneg_int, out_path, positive_int, seed
from mvgeo.common.atomic import atomic_output_dir, atomic_write_text
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.deps import cv2
from mvgeo.common.device import DEVICE_HELP, resolve_device
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import check_distinct_stems, list_images, read_image, write_image
from mvgeo.common.output import OUT_HELP, OVERWRITE_HELP, prepare_output, prepare_output_file, write_output_file
from mvgeo.common.timing import StageTimer

_log = logging.getLogger(__name__)


def _bit_depth(path: Path) -> int:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return 16 if img is not None and img.dtype == np.uint16 else 8


def contact_sheet(noisy: Sequence[np.ndarray], denoised: Sequence[np.ndarray], *, max_rows: int = 6,
                  height_px: int = 160) -> np.ndarray:
    """Rows of ``noisy | denoised`` pairs (first `max_rows` images), each row `height_px` high.

    Returns:
        ``(H, W, 3)`` float32 in [0, 1], white gutters.
    """
    rows = []
    for a, b in list(zip(noisy, denoised, strict=True))[:max_rows]:
        pair = []
        for im in (a, b):
            im = np.asarray(im, np.float32)
            im = np.repeat(im[..., None], 3, 2) if im.ndim == 2 else (np.repeat(im, 3, 2) if im.shape[2] == 1 else im)
            w = max(1, round(im.shape[1] * height_px / im.shape[0]))
            pair.append(cv2.resize(im, (w, height_px), interpolation=cv2.INTER_AREA))
        gutter = np.ones((height_px, 4, 3), np.float32)
        rows.append(np.concatenate([pair[0], gutter, pair[1]], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
    return np.concatenate(rows, axis=0)


def _cmd_n2v(args: argparse.Namespace) -> int:
    from denoise.images import MIN_SIDE_PX

    device = resolve_device(args.device)
    plan = prepare_output(args.out, command="denoise n2v", inputs=[args.images_dir], overwrite=args.overwrite)
    files = list_images(args.images_dir)
    check_distinct_stems([f.name for f in files], path=args.images_dir)  # one output file per image
    images = [read_image(f, gray_to_rgb=False) for f in files]  # gray stays (H, W, 1): written back as gray
    for f, img in zip(files, images, strict=True):
        if min(img.shape[:2]) < MIN_SIDE_PX:
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} px; N2V needs at least "
                             f"{MIN_SIDE_PX}x{MIN_SIDE_PX}", path=f, fix="remove it from the folder")
    overrides = {} if args.steps is None else {"steps": args.steps}
    levels = stride_for(images, args.pd_stride, hint=args.noise_model == "auto")
    stride, chosen = levels.stride, levels.record()
    work = images
    small = [f for f, img in zip(files, images, strict=True) if min(img.shape[:2]) < MIN_SIDE_PX * stride]
    if small:
        raise InputError(f"image is too small for --pd-stride {stride}: its sub-images would be under "
                         f"{MIN_SIDE_PX} px", path=small[0], fix="give a smaller --pd-stride, or 1")
    if stride > 1:
        _log.info("denoising the %d x %d pixel-shuffled sub-images of each image (noise correlated between "
                  "neighbouring pixels; its level /255 by stride: %s)", stride, stride,
                  levels.levels_255())
        work = shuffled(images, stride)
    if levels.hint() is not None and args.noise_model == "auto":
        _log.warning("%s", levels.hint())
    if levels.luma_level is not None:
        _log.info("the images' colour patches read %.1f/255 of noise, their luma %.1f/255: chroma-subsampled noise, "
                  "as a JPEG's; its level is read on the luma", 255.0 * levels.level_by_stride[1],
                  255.0 * levels.luma_level)
    method = args.method
    if method == "auto":  # on the whole images: the dark fraction's blur is in pixels of the image
        choice = choose_objective(images)
        method = choice.method
        chosen.update({"objective_rule": "auto", "dark_clipped_fraction": round(choice.dark_clipped_fraction, 4)})
    noise_model = levels.noise_model if args.noise_model == "auto" else args.noise_model
    config = n2v_preset(args.preset, **overrides, method=method)
    grouped = args.grouped_wiener or args.grouped_wiener_passes > 1
    timer = StageTimer()
    with timer.stage("train"):
        model = train_with_method(work, config, seed=args.seed, device=device, noise_model=noise_model)
    with timer.stage("denoise"):
        out = denoise_with_method(model, work, config, passes=args.passes, seed=args.seed,
                                  noise_model=noise_model, wiener=WienerConfig() if args.wiener else None,
                                  grouped=GroupedWienerConfig(passes=args.grouped_wiener_passes)
                                  if grouped else None)
        if stride > 1:
            out = unshuffled(out, stride, [im.shape for im in images])
    with atomic_output_dir(plan) as tmp:
        (tmp / "images").mkdir()
        for f, img in zip(files, out, strict=True):
            write_image(tmp / "images" / (f.stem + ".png"), img, bits=_bit_depth(f))
        save_checkpoint(tmp / "model.pt", model)
        write_image(tmp / "contact_sheet.png", contact_sheet(images, out))
        atomic_write_text(tmp / "report.json", json.dumps({
            "images": [f.name for f in files], "preset": args.preset, "method": config.method,
            "steps": config.steps,
            "passes": args.passes, "noise_model": noise_model, "seed": args.seed, "wiener": args.wiener,
            "grouped_wiener": grouped, "grouped_wiener_passes": args.grouped_wiener_passes if grouped else 0,
            "final_loss": float(np.mean(model.history[-20:])),
            "timing_s": timer.as_dict(), **chosen}, indent=2))
    _log.info("wrote %d denoised images, model.pt and contact_sheet.png to %s", len(out), args.out)
    return 0


def _cmd_select(args: argparse.Namespace) -> int:
    from mvgeo.common.imageio import upright_size
    from mvgeo.sparse_model import read_sparse_model

    out = None
    if args.out is not None:  # the resolved file: a symbolic link given as --out is written through, not replaced
        out = prepare_output_file(args.out, command="denoise select", inputs=[args.sparse_dir, args.images],
                                  overwrite=args.overwrite, example_name="selection.json")
    model = read_sparse_model(args.sparse_dir)
    images_dir = Path(args.images)
    poses, paths = {}, {}
    for im in model.images:
        path = images_dir / im.name
        if not path.is_file():
            raise InputError(f"image {im.name!r} of the sparse model is missing", path=path,
                             fix="pass the folder holding the model's images with --images")
        cam, wh = model.camera_of(im.name), upright_size(path)
        if wh is not None and wh != (cam.width, cam.height):
            raise InputError(f"image {im.name!r} is {wh[0]}x{wh[1]} but its camera in the sparse model is "
                             f"{cam.width}x{cam.height}", path=path,
                             fix="pass the images the model was made from, at their size, with --images")
        poses[im.name] = im.cam_from_world
        paths[im.name] = path
    sel = select_views(poses, paths, k=args.k, seed=args.seed)
    text = json.dumps(sel.to_json_dict(), indent=2)
    if out is not None:
        write_output_file(out, "denoise select", lambda tmp: tmp.write_text(text + "\n", encoding="utf-8"))
    print(text)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="denoise", description="Noise2Void denoising and round-2 view selection.")
    add_common_args(parser)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("n2v", help="train N2V on a folder of noisy images and denoise them")
    p.add_argument("images_dir", help="folder of noisy images (PNG/JPEG, 8/16-bit, RGB or gray)")
    p.add_argument("--out", type=out_path, required=True,
                   help="output folder: images/, model.pt, contact_sheet.png, report.json; " + OUT_HELP)
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--steps", type=positive_int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--passes", type=nonneg_int, default=8, help="random maskings averaged; 0 = one unmasked pass")
    p.add_argument("--preset", choices=sorted(N2V_PRESETS), default="default", help="training preset")
    p.add_argument("--method", choices=(*METHODS, "auto"), default="n2v",
                   help="self-supervised objective on the same UNet: n2v (blind spot), neighbor2neighbor, "
                        "r2r (recorrupted-to-recorrupted, noise level estimated per image), or auto (r2r, or "
                        "neighbor2neighbor where more than a fifth of the photos is black and clipped: R2R's "
                        "recorruption fails there; what `denoise-gs run` uses by default)")
    p.add_argument("--noise-model", choices=NOISE_MODELS, default="auto",
                   help="noise level for n2v's centre-pixel fusion and r2r's recorruption: one per image "
                        "(constant: Gaussian noise), a per-intensity curve (signal-dependent, Poisson-Gaussian "
                        "noise), the constant read on the luma (luma: a JPEG's chroma-subsampled noise), or auto "
                        "(the curve where shot noise dominates, per image; luma where the photos' noise is "
                        "chroma-subsampled)")
    p.add_argument("--wiener", action="store_true",
                   help="refine the network's output with the sliding-window DCT Wiener step (denoise.wiener: "
                        "the noisy image shrunk by the gains the output implies; about +0.9-1.8 dB on real photos)")
    p.add_argument("--grouped-wiener", action="store_true",
                   help="then the grouped Wiener step (denoise.grouped_wiener: similar patches of the noisy image "
                        "filtered together with the statistics of the output so far; about 1.5 s per 384x384 photo "
                        "on 2 cores)")
    p.add_argument("--grouped-wiener-passes", type=positive_int, default=1, metavar="N",
                   help="N passes of the grouped Wiener step (N > 1 turns it on), each with the previous one's "
                        "output as its pilot and 80 patches per group after the first (default 1)")
    p.add_argument("--pd-stride", type=int_range(0, MAX_STRIDE), default=0, metavar="N",
                   help="denoise the pixel-shuffled sub-images of every N-th pixel, for noise correlated between "
                        "neighbouring pixels as a camera's demosaicing leaves it (denoise.pixel_shuffle). 0 "
                        f"(default) = measured from the images (1 for independent noise), 1 = off, 2-{MAX_STRIDE} = "
                        "that stride")
    p.add_argument("--seed", type=seed, default=0)
    p.add_argument("--device", default="cpu", help=DEVICE_HELP + " (training and inference); default cpu")
    p.set_defaults(func=_cmd_n2v)
    s = sub.add_parser("select", help="choose round-2 views by pose clustering and sharpness")
    s.add_argument("sparse_dir", help="COLMAP model folder (cameras/images/points3D .txt or .bin)")
    s.add_argument("--images", required=True, help="folder with the model's images")
    s.add_argument("--k", type=positive_int, default=12, help="number of views to select (k >= N keeps all)")
    s.add_argument("--seed", type=seed, default=0)
    s.add_argument("--out", type=out_path, default=None,
                   help="also write the JSON to this file (a new file; not a folder)")
    s.add_argument("--overwrite", action="store_true",
                   help="replace the --out file when this command wrote it and it is unchanged "
                        "(nothing else is ever replaced)")
    s.set_defaults(func=_cmd_select)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(lambda a: a.func(a), build_parser(), argv)


if __name__ == "__main__":
    raise SystemExit(main())
