"""Write a `Capture` as the project's dataset layout (what `denoise-gs eval` reads).

    OUT/
      clean/NAME.png    the photograph, resized if asked (8-bit, 16-bit when the source is)
      images/NAME.png   the same with the declared degradation; byte-identical to clean/ without one
      sparse/0/         ground-truth cameras (COLMAP text; one camera per view) and the source model's
                        points, if any
      split.json        {"train": [...], "test": [...]} file names
      meta.json         importer, source, conversions, split rule, sizes, noise model and seed

Only the training and held-out views are written. The photographs are taken as
stored: an EXIF Orientation tag (phone JPEGs) is not applied, since every
format's cameras describe the stored pixel array (COLMAP, and LLFF's poses
computed by it, ignore the tag; `eval.real.capture.image_size_wh` reads the
stored size). Resizing uses OpenCV's area
filter; in our pixel convention (image spanning [0, W] x [0, H]) a resize maps
``u -> u W'/W``, ``v -> v H'/H`` exactly, so the intrinsics scale exactly
(`mvgeo.camera.Camera.scaled`).

The folder is written atomically under the project's output policy
(`mvgeo.common.output`, command `denoise-gs dataset import`): OUT may be new
or empty, or a previous import replaced with `overwrite`; anything else, and
an OUT that is, holds or lies inside the source, is refused before any image
is read.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np

from eval.real.capture import Capture
from eval.real.degrade import Degradation, parse_noise
from eval.real.split import cluster_split, every_kth_split, ring_split, spread_split
from mvgeo.common.atomic import atomic_output_dir, atomic_write_text
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, to_uint
from mvgeo.common.output import OutputPlan, prepare_output
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model

__all__ = ["COMMAND", "FORMAT_VERSION", "ImportConfig", "choose_split", "output_plan", "output_size_wh",
           "write_capture"]

_log = logging.getLogger(__name__)
FORMAT_VERSION = 1
#: The command name in the output manifest (`mvgeo.common.output`).
COMMAND = "denoise-gs dataset import"
#: Held-out rule when none is given: LLFF's every 8th view.
DEFAULT_TEST_EVERY = 8


@dataclass(frozen=True)
class ImportConfig:
    """How a capture becomes a dataset.

    Attributes:
        views: training views (spread over the candidates); None takes every non-held-out view
            (`spread` layout) or 12 (`cluster`, `ring`).
        test_every: hold out views 0, K, 2K, ... (LLFF's convention; default 8 when neither this nor
            `test` is given with the `spread` layout).
        test: hold out this many views instead, midway between the training views (`spread`) or inside
            them (`cluster`, default 4).
        layout: "spread" (views over the capture's order), "cluster" (the most alike viewing
            directions, `eval.real.split.cluster_split`) or "ring" (an orbit: training views spread
            by angle around the camera centres' ring, held out the views between them,
            `eval.real.split.ring_split`).
        size_wh: output (width, height) in pixels; None keeps the source size (or `max_size_px`).
        max_size_px: downscale so that the longer side is at most this; None: no limit.
        noise: the declared degradation (`eval.real.degrade.parse_noise`).
        seed: the noise seed.
        overwrite: replace an OUT holding a previous import (never anything else).
    """

    views: int | None = None
    test_every: int | None = None
    test: int | None = None
    layout: str = "spread"
    size_wh: tuple[int, int] | None = None
    max_size_px: int | None = None
    noise: Degradation = field(default_factory=lambda: parse_noise(None))
    seed: int = 0
    overwrite: bool = False


def choose_split(capture: Capture, config: ImportConfig) -> tuple[list[int], list[int], dict]:
    """(training indices, held-out indices, the rule as recorded in meta.json).

    Raises:
        InputError: conflicting or impossible options.
    """
    n = len(capture.views)
    if config.test_every is not None and config.test is not None:
        raise InputError("give either --test-every or --test, not both")
    if config.layout == "spread":
        if config.test is not None:
            train = n - config.test if config.views is None else config.views
            tr, te = spread_split(n, train, config.test)
            rule = {"layout": "spread", "views": train, "test": config.test}
        else:
            k = DEFAULT_TEST_EVERY if config.test_every is None else config.test_every
            tr, te = every_kth_split(n, k, config.views)
            rule = {"layout": "every_kth", "views": len(tr), "test_every": k}
    elif config.layout == "cluster":
        if config.test_every is not None:
            raise InputError("--test-every does not apply to the cluster layout", fix="use --test N")
        train = 12 if config.views is None else config.views
        test = 4 if config.test is None else config.test
        dirs = np.array([v.cam_from_world[2, :3] for v in capture.views])
        tr, te = cluster_split(dirs, train, test)
        rule = {"layout": "cluster", "views": train, "test": test}
    elif config.layout == "ring":
        if config.test_every is not None:
            raise InputError("--test-every does not apply to the ring layout", fix="use --test N")
        train = 12 if config.views is None else config.views
        centres = np.array([-v.cam_from_world[:3, :3].T @ v.cam_from_world[:3, 3] for v in capture.views])
        tr, te = ring_split(centres, train, config.test)
        rule = {"layout": "ring", "views": train, "test": len(te)}
    else:
        raise InputError(f"unknown split layout {config.layout!r}", fix='use "spread", "cluster" or "ring"')
    if len(tr) < 2 or not te:
        raise InputError(f"the split of {n} views leaves {len(tr)} training and {len(te)} held-out views",
                         fix="a dataset needs at least 2 training views and 1 held-out view")
    return tr, te, rule


def output_size_wh(size_wh: tuple[int, int], config: ImportConfig) -> tuple[int, int]:
    """The written size of an image of `size_wh` under `config` (--size, --max-size)."""
    w, h = size_wh
    if config.size_wh is not None:
        return int(config.size_wh[0]), int(config.size_wh[1])
    if config.max_size_px is not None and max(w, h) > config.max_size_px:
        s = config.max_size_px / max(w, h)
        return max(1, round(w * s)), max(1, round(h * s))
    return w, h


def _check_config(config: ImportConfig) -> None:
    if config.size_wh is not None and config.max_size_px is not None:
        raise InputError("give either --size or --max-size, not both")
    if config.size_wh is not None and min(config.size_wh) < 8:
        raise InputError(f"--size must be at least 8x8 pixels, got {config.size_wh[0]}x{config.size_wh[1]}")
    if config.max_size_px is not None and config.max_size_px < 8:
        raise InputError(f"--max-size must be at least 8 pixels, got {config.max_size_px}")
    if config.views is not None and config.views < 2:
        raise InputError(f"--views must be at least 2, got {config.views}")
    if config.test is not None and config.test < 1:
        raise InputError(f"--test must be at least 1, got {config.test}")
    if not 0 <= config.seed < 2**32:
        raise InputError(f"--seed must be in [0, 2^32 - 1], got {config.seed}")


def output_plan(out: str | Path | OutputPlan, *, sources: tuple[str | Path, ...], overwrite: bool) -> OutputPlan:
    """`out` checked against the output policy (or a plan made by the command line), before any work.

    Raises:
        InputError: OUT is refused (a folder holding other files, a file, an input, ...).
    """
    if isinstance(out, OutputPlan):
        if out.command != COMMAND:
            raise ValueError(f"output plan of {out.command!r} passed to the importer")
        return out
    return prepare_output(out, command=COMMAND, inputs=sources, overwrite=overwrite)


def _bits_of(path: Path) -> int:
    if path.suffix.lower() not in (".png", ".tif", ".tiff"):
        return 8
    img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    return 16 if img is not None and img.dtype == np.uint16 else 8


def _png_bytes(img: np.ndarray, bits: int) -> bytes:
    arr = to_uint(img, bits)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr[:, :, ::-1]))
    if not ok:
        raise RuntimeError("PNG encoding failed")  # cv2 encodes any uint8/uint16 (H, W, 3) array
    return buf.tobytes()


def _package_version() -> str:
    try:
        return metadata.version("denoise-gs")
    except metadata.PackageNotFoundError:
        return "unknown"


def write_capture(capture: Capture, out: str | Path | OutputPlan, config: ImportConfig) -> Path:
    """Write `capture` as a dataset folder `out` (a path, or a plan from `output_plan`; module docstring).

    Every check (options, split, output folder, noise parameters) runs before any image is read; an
    error while writing leaves `out` as it was.

    Returns:
        The dataset folder (absolute).

    Raises:
        InputError: bad options, an impossible split, an output folder we may not replace, unreadable
            images.
    """
    _check_config(config)
    tr, te, rule = choose_split(capture, config)
    plan = output_plan(out, sources=capture.inputs, overwrite=config.overwrite)
    chosen = sorted(tr + te)
    cameras, images, view_meta = {}, [], {}
    with atomic_output_dir(plan) as tmp:
        for sub in ("images", "clean"):
            (tmp / sub).mkdir()
        for cam_id, i in enumerate(chosen, start=1):
            view = capture.views[i]
            img = read_image(view.image_path, apply_orientation=False)  # the pixels the camera describes
            h, w = img.shape[:2]
            if (w, h) != view.camera.size_wh:
                raise InputError(f"the image is {w}x{h} but its camera is {view.camera.width}x"
                                 f"{view.camera.height}", path=view.image_path)
            out_w, out_h = output_size_wh((w, h), config)
            camera = view.camera
            if (out_w, out_h) != (w, h):
                img = cv2.resize(img, (out_w, out_h), interpolation=cv2.INTER_AREA)
                camera = camera.scaled(out_w, out_h)
            bits = _bits_of(view.image_path)
            file = f"{view.name}.png"
            clean = _png_bytes(img, bits)
            (tmp / "clean" / file).write_bytes(clean)
            if config.noise.is_none:
                (tmp / "images" / file).write_bytes(clean)
            else:
                clean_q = to_uint(img, bits).astype(np.float32) / np.float32(255 if bits == 8 else 65535)
                noisy = config.noise.apply(clean_q, seed=config.seed, view_name=view.name, K=camera.K)
                (tmp / "images" / file).write_bytes(_png_bytes(noisy, bits))
            cameras[cam_id] = camera
            images.append(PosedImage(file, cam_id, view.cam_from_world[:3]))
            view_meta[file] = {"source_image": str(view.image_path), "source_index": i,
                               "source_size_wh": [w, h], "size_wh": [out_w, out_h], "bits": bits,
                               "near_far": None if view.near_far is None else list(view.near_far)}
        write_sparse_model(tmp / "sparse" / "0", SparseModel(cameras, images, capture.points_xyz,
                                                             capture.points_rgb), binary=False)
        split = {"train": [f"{capture.views[i].name}.png" for i in tr],
                 "test": [f"{capture.views[i].name}.png" for i in te]}
        atomic_write_text(tmp / "split.json", json.dumps(split, indent=2) + "\n")
        sphere = capture.sphere
        meta = {
            "format_version": FORMAT_VERSION,
            "written_by": COMMAND,
            "version": _package_version(),
            "importer": capture.kind,
            "source": str(Path(capture.source).resolve()),
            "world_units": capture.world_units,
            "bounding_sphere": None if sphere is None else {"centre_world": list(sphere.centre_world),
                                                            "radius": sphere.radius},
            "conversions": list(capture.notes),
            "split": rule,
            "resize": {"size_wh": None if config.size_wh is None else list(config.size_wh),
                       "max_size_px": config.max_size_px, "filter": "cv2.INTER_AREA"},
            "noise": config.noise.meta(config.seed),
            "views": view_meta,
        }
        atomic_write_text(tmp / "meta.json", json.dumps(meta, indent=2) + "\n")
    _log.info("wrote %d views (%d train, %d test) to %s", len(chosen), len(tr), len(te), plan.out)
    return plan.path

