"""pycolmap SfM (the reference the alignment is checked against): `mvgeo colmap`.

CPU SIFT, exhaustive matching, then incremental mapping (default) or global
mapping (GLOMAP inside pycolmap) into the same output layout as `mvgeo align`:
`OUT/sparse/0/*.bin` and `OUT/colmap.json` (timings, registered images).
One shared camera (SIMPLE_RADIAL, COLMAP's default for unknown cameras).
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.deps import pycolmap
from mvgeo.common.errors import DegenerateGeometryError, InputError
from mvgeo.common.imageio import list_images, read_image
from mvgeo.common.output import OutputPlan, as_output_plan
from mvgeo.common.timing import StageTimer
from mvgeo.sparse_model import SparseModel, from_pycolmap, write_sparse_model

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ColmapConfig:
    """Options of the pycolmap run.

    Attributes:
        mapper: "incremental" or "global".
        max_image_size_px: SIFT extraction image size limit (COLMAP's default 3200).
        num_threads: CPU threads (-1: all).
        single_camera: one shared camera for all images.
        camera_model: COLMAP camera model to estimate.
        known_pinhole: (fx, fy, cx, cy) in pixels (COLMAP's convention: the top-left pixel's corner at 0)
            of a known PINHOLE camera shared by all images, kept fixed by the mapper's bundle adjustment
            (the counterpart of `mvgeo align --intrinsics`); None: `camera_model` is estimated.
    """

    mapper: str = "incremental"
    max_image_size_px: int = 3200
    num_threads: int = -1
    single_camera: bool = True
    camera_model: str = "SIMPLE_RADIAL"
    known_pinhole: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class ColmapStats:
    """The report of a pycolmap run (`OUT/colmap.json`, `to_json`).

    Attributes:
        mapper: "incremental" or "global".
        n_images: images given.
        n_registered: images in the largest model.
        n_models: models the mapper returned.
        unregistered: names of the images outside the largest model, sorted.
        n_points: 3D points of the largest model.
        timings_s: seconds per stage (features, matching, mapping) and "total".
    """

    mapper: str
    n_images: int
    n_registered: int
    n_models: int
    unregistered: list[str]
    n_points: int
    timings_s: dict[str, float]

    def to_json(self) -> dict[str, object]:
        """colmap.json's content."""
        return asdict(self)


@dataclass
class ColmapResult:
    """The largest reconstruction and its report."""

    sparse_model: SparseModel
    stats: ColmapStats


def run_colmap(images_dir: str | Path, config: ColmapConfig = ColmapConfig(), *,
               image_names: list[str] | None = None) -> ColmapResult:
    """Run pycolmap SfM on the images in `images_dir` (or the listed names).

    Raises:
        InputError: missing/empty folder or unreadable image.
        DegenerateGeometryError: COLMAP registered no model.
    """
    images_dir = Path(images_dir)
    paths = list_images(images_dir)
    names = image_names if image_names is not None else [p.name for p in paths]
    if len(names) < 2:
        raise InputError(f"need at least 2 images, got {len(names)}", path=images_dir,
                         fix="put the photos (PNG or JPEG) of one scene in the folder, at least two")
    for n in names:
        read_image(images_dir / n)  # named InputError for corrupt files (COLMAP would skip them silently)
    if config.mapper not in ("incremental", "global"):
        raise InputError(f"unknown mapper {config.mapper!r}", fix="use incremental or global")
    timer = StageTimer()
    work = Path(tempfile.mkdtemp(prefix="mvgeo-colmap-"))
    try:
        db = work / "database.db"
        ext = pycolmap.FeatureExtractionOptions()
        ext.max_image_size = config.max_image_size_px
        ext.num_threads = config.num_threads
        ext.use_gpu = False
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = config.camera_model
        if config.known_pinhole is not None:
            reader.camera_model = "PINHOLE"
            reader.camera_params = ",".join(repr(float(v)) for v in config.known_pinhole)
        mode = pycolmap.CameraMode.SINGLE if config.single_camera else pycolmap.CameraMode.AUTO
        with timer.stage("features"):
            pycolmap.extract_features(db, images_dir, image_names=names, camera_mode=mode, reader_options=reader,
                                      extraction_options=ext, device=pycolmap.Device.cpu)
        with timer.stage("matching"):
            pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        with timer.stage("mapping"):
            if config.mapper == "incremental":
                opts = pycolmap.IncrementalPipelineOptions()
                opts.num_threads = config.num_threads
                if config.known_pinhole is not None:
                    opts.ba_refine_focal_length = False
                    opts.ba_refine_principal_point = False
                    opts.ba_refine_extra_params = False
                recs = pycolmap.incremental_mapping(db, images_dir, work / "sparse", options=opts)
            else:
                gopts = pycolmap.GlobalPipelineOptions()
                if config.known_pinhole is not None:
                    gopts.mapper.bundle_adjustment.refine_focal_length = False
                    gopts.mapper.bundle_adjustment.refine_principal_point = False
                    gopts.mapper.bundle_adjustment.refine_extra_params = False
                recs = pycolmap.global_mapping(db, images_dir, work / "sparse", options=gopts)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not recs:
        raise DegenerateGeometryError("COLMAP could not reconstruct any model from these images")
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    model = from_pycolmap(best)
    stats = ColmapStats(mapper=config.mapper, n_images=len(names), n_registered=len(model.images),
                        n_models=len(recs), unregistered=sorted(set(names) - set(model.names)),
                        n_points=int(len(model.points_xyz)), timings_s=timer.as_dict())
    return ColmapResult(model, stats)


def write_colmap_result(out: str | Path | OutputPlan, result: ColmapResult, *, overwrite: bool = False) -> Path:
    """Write `OUT/sparse/0/*.bin` and `OUT/colmap.json` atomically.

    `out` is a folder or the plan `prepare_output(..., command="mvgeo colmap")` made for it; a
    previous `mvgeo colmap` output there is replaced only with `overwrite` (see `mvgeo.common.output`).
    """
    plan = as_output_plan(out, command="mvgeo colmap", overwrite=overwrite)
    with atomic_output_dir(plan) as tmp:
        write_sparse_model(tmp / "sparse" / "0", result.sparse_model, binary=True)
        (tmp / "colmap.json").write_text(json.dumps(result.stats.to_json(), indent=2))
    return plan.out
