"""Render a resolved scene into a dataset folder (the format every other tool reads).

    OUT/
      images/VIEW.png   degraded images (what a pipeline sees), 8-bit unless render.bit_depth = 16
      clean/VIEW.png    ground truth, same bit depth
      depth/VIEW.npy    float32 (H, W) z-depth of the pixel-centre ray, inf where it misses
                        (only when render.outputs has "depth")
      alpha/VIEW.npy    float32 (H, W) coverage (only when asked)
      normals/VIEW.npy  float32 (H, W, 3) camera-frame unit normals, 0 on a miss (only when asked)
      sparse/0/         ground-truth cameras: cameras.txt, images.txt, empty points3D.txt (COLMAP text)
      split.json        {"train": [...], "test": [...]} of image file names
      scene.toml        the resolved scene, seed included (re-renders this dataset)
      meta.json         version, sizes, per-stage timings
      .denoise-gs-output.json  the output manifest (command, version, time: `mvgeo.common.output`)

The folder is written atomically (a temporary sibling renamed at the end); an existing
folder is replaced only when it is a dataset written before and `overwrite` is set.
With no effects, `images/` files are byte-identical to `clean/` files.
"""

from __future__ import annotations

import json
import logging
import platform
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_synth.effects import EffectContext, apply_effects, effects_need
from data_synth.intrinsics import camera_from_spec
from data_synth.render import SceneRenderer, check_render_memory
from data_synth.rigs import View, rig_views, split_views
from data_synth.scene_file import scene_to_toml
from data_synth.spec import SceneSpec
from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.deps import cv2
from mvgeo.common.imageio import to_uint
from mvgeo.common.output import OutputPlan, as_output_plan
from mvgeo.common.progress import progress
from mvgeo.common.timing import StageTimer
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model

_log = logging.getLogger(__name__)
FORMAT_VERSION = 1
#: The command named in the output manifest of a dataset folder.
DATASET_COMMAND = "data-synth render"
CAMERA_ID = 1


@dataclass(frozen=True)
class Needs:
    """Which optional render outputs are computed (for writing or for an effect)."""

    depth: bool
    alpha: bool
    normals: bool


def render_needs(spec: SceneSpec) -> Needs:
    """Depth/alpha/normals are computed only when an output or an effect needs them."""
    wanted = set(spec.render.outputs) | set(effects_need(spec.effects))
    return Needs(depth="depth" in wanted, alpha="alpha" in wanted, normals="normals" in wanted)


def _png_bytes(img: np.ndarray, bits: int) -> bytes:
    arr = to_uint(img, bits)[:, :, ::-1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise RuntimeError("OpenCV failed to encode a PNG")
    return buf.tobytes()


def sparse_model_of(spec: SceneSpec, views: list[View], *, suffix: str = ".png") -> SparseModel:
    """Ground-truth cameras: one shared camera, one image per view (no 3-D points)."""
    camera = camera_from_spec(spec.camera, tuple(spec.render.size))
    images = [PosedImage(v.name + suffix, CAMERA_ID, v.cam_from_world) for v in views]
    return SparseModel(cameras={CAMERA_ID: camera}, images=images)


def write_dataset(spec: SceneSpec, out: str | Path | OutputPlan, *, overwrite: bool = False) -> Path:
    """Render every view of `spec` into the dataset folder `out` (see module docstring).

    Args:
        spec: a resolved scene (`data_synth.load_scene`).
        out: output folder (written atomically when complete), or the plan
            `prepare_output(..., command="data-synth render")` made for it.
        overwrite: a previous dataset written here (by `data-synth render` / `write_dataset`) may be
            replaced; anything else at `out` is refused (`mvgeo.common.output`).

    Returns:
        The output folder.

    Raises:
        InputError: `out` is refused by the output policy.
    """
    plan = as_output_plan(out, command=DATASET_COMMAND, overwrite=overwrite)
    out = plan.out
    timer = StageTimer()
    needs = render_needs(spec)
    check_render_memory(spec)  # before any work: one view's rays must fit in memory
    bits = spec.render.bit_depth
    with timer.stage("setup"):
        renderer = SceneRenderer.from_spec(spec)
        views = rig_views(spec.rig)
        camera = camera_from_spec(spec.camera, tuple(spec.render.size))
    with atomic_output_dir(plan) as tmp:
        folders = ["images", "clean"] + [n for n, on in (("depth", needs.depth and "depth" in spec.render.outputs),
                                                         ("alpha", needs.alpha), ("normals", needs.normals)) if on]
        for f in folders:
            (tmp / f).mkdir()
        for view in progress(views, desc=f"render {spec.info.name}", unit="view"):
            with timer.stage("render"):
                r = renderer.render(camera, view.cam_from_world, supersample=spec.render.supersample,
                                    depth=needs.depth, alpha=needs.alpha, normals=needs.normals)
            with timer.stage("effects"):
                if spec.effects:
                    ctx = EffectContext(view_name=view.name, K=camera.K, depth=r.depth)
                    degraded = apply_effects(r.rgb, spec.effects, seed=spec.info.seed, ctx=ctx)
                else:
                    degraded = None
            with timer.stage("write"):
                clean_png = _png_bytes(r.rgb, bits)
                (tmp / "clean" / f"{view.name}.png").write_bytes(clean_png)
                images_png = clean_png if degraded is None else _png_bytes(degraded, bits)
                (tmp / "images" / f"{view.name}.png").write_bytes(images_png)
                if "depth" in spec.render.outputs:
                    np.save(tmp / "depth" / f"{view.name}.npy", r.depth)
                if needs.alpha:
                    np.save(tmp / "alpha" / f"{view.name}.npy", r.alpha)
                if needs.normals:
                    np.save(tmp / "normals" / f"{view.name}.npy", r.normals)
        with timer.stage("write"):
            write_sparse_model(tmp / "sparse" / "0", sparse_model_of(spec, views), binary=False)
            split = split_views([v.name for v in views], spec.split)
            split_files = {k: [f"{n}.png" for n in names] for k, names in split.items()}
            (tmp / "split.json").write_text(json.dumps(split_files, indent=2) + "\n")
            (tmp / "scene.toml").write_text(scene_to_toml(spec))
        meta = {
            "format": "data_synth dataset",
            "format_version": FORMAT_VERSION,
            "generator": f"data_synth {_package_version()}",
            "scene": spec.info.name,
            "seed": spec.info.seed,
            "size_wh": list(spec.render.size),
            "supersample": spec.render.supersample,
            "bit_depth": bits,
            "views": len(views),
            "camera_model": camera.model,
            "effects": [e.type for e in spec.effects],
            "outputs": {"depth": "depth" in spec.render.outputs, "alpha": needs.alpha, "normals": needs.normals},
            "depth": {"kind": "z", "frame": "camera (OpenCV axes)", "miss": "inf", "dtype": "float32"},
            "timings_s": timer.as_dict(),
            "host": {"python": platform.python_version(), "machine": platform.machine()},
        }
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    _log.info("wrote %d views of %s to %s", len(views), spec.info.name, out)
    return out


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return version("denoise-gs")
    except Exception:  # not installed (running from a checkout)
        return "0+unknown"
