"""The working images of a run: the input photos upright (EXIF orientation) and downscaled once.

`denoise-gs run --max-size N` (default 512, InstantSplat's working size) fixes the long side of
the images every stage works on. Each input larger than that is resized once, with the area
filter (each output pixel the mean of the input pixels it covers: no aliasing of noise or
texture), and written as a 16-bit PNG into `OUT/inputs/`; smaller inputs are copied unchanged
(8-bit values survive 16-bit PNG exactly). `OUT/inputs/sizes.json` keeps each view's input and
working size, so the final cameras can also be written at the input resolution and under the photo's
file name (`eval.pipeline.publish`), and the photo's EXIF 35 mm-equivalent focal length (`focal_35mm`, null
without one), which the PNGs do not carry: the alignment starts at it (`working_focal_prior`).

Every stage assumes one camera, so the working images share one size (`reference_working_size`: the
most common one). A portrait photo among landscape ones (or the reverse) is the same camera turned by 90
degrees: its working image is turned a quarter counter-clockwise (`np.rot90`) to the common orientation,
and `sizes.json` records `turned: 1` for it; its camera in `cameras/input/` is turned back
(`eval.pipeline.publish.turn_back`). The round folders' photos and renders keep the working orientation.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from eval.pipeline.stage import (
    RECORD_DIR,
    StageContext,
    commit_written,
    verify_outputs,
)
from eval.pipeline.summaries import InputsSummary, WorkingSize
from eval.pipeline.views import view_files, write_views
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import exif_focal_35mm, read_image

__all__ = ["DATA_DIR", "SIZES_FILE", "WORKING_DIR", "prepare_inputs", "read_sizes", "reference_working_size",
           "nearest_depth", "resize_area", "working_dataset", "working_focal_prior", "working_size"]

#: Folder of the working images inside OUT, and the sizes file inside it.
WORKING_DIR = "inputs"
SIZES_FILE = "sizes.json"
#: Folder of an evaluation's datasets inside its OUT (`working_dataset`); each working-size dataset's record
#: is `DATA_DIR/stages/<its name>.json`.
DATA_DIR = "data"


def working_size(width: int, height: int, max_size: int | None) -> tuple[int, int]:
    """(W, H) of the working image: unchanged when the long side is <= `max_size` (or None), else
    scaled so the long side is `max_size`, the short side rounded (at least 1)."""
    if max_size is None or max(width, height) <= max_size:
        return int(width), int(height)
    s = max_size / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def reference_working_size(sizes_wh: Sequence[tuple[int, int]]) -> tuple[int, int]:
    """The (W, H) the working images share: the most common of `sizes_wh` (ties: the first seen). A size
    that is its transpose (a photo turned by 90 degrees) is turned to it (module docstring)."""
    if not sizes_wh:
        raise ValueError("no image sizes")
    return Counter(tuple(s) for s in sizes_wh).most_common(1)[0][0]  # equal counts: in first-seen order


def resize_area(img: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """(H, W, C) float image -> (h, w, C) with the area filter (`cv2.INTER_AREA`); unchanged when
    the size already matches."""
    from mvgeo.common.deps import cv2

    w, h = size_wh
    if img.shape[1] == w and img.shape[0] == h:
        return img
    if w > img.shape[1] or h > img.shape[0]:
        raise ValueError(f"resize_area only downscales: {img.shape[1]}x{img.shape[0]} -> {w}x{h}")
    return cv2.resize(np.ascontiguousarray(img, np.float32), (w, h), interpolation=cv2.INTER_AREA)


def prepare_inputs(ctx: StageContext) -> Mapping[str, object]:
    """Stage `inputs`: `ctx.inputs["noisy"]` -> `WORKING_DIR/<stem>.png` at the working size
    (`ctx.settings`: `InputsStageSettings`) and `WORKING_DIR/sizes.json`; returns an `InputsSummary`'s JSON."""
    max_size = ctx.settings.max_size
    out = ctx.work_dir / WORKING_DIR
    sizes: dict[str, WorkingSize] = {}
    images = {}
    for stem, path in view_files(Path(ctx.inputs["noisy"])).items():
        img = read_image(path)
        size = working_size(img.shape[1], img.shape[0], max_size)
        images[stem] = resize_area(img, size)
        sizes[stem] = WorkingSize((img.shape[1], img.shape[0]), (int(size[0]), int(size[1])), exif_focal_35mm(path),
                                  file=path.name)
    ref = reference_working_size([v.working_wh for v in sizes.values()])
    for stem, v in list(sizes.items()):
        if v.working_wh != ref and v.working_wh == ref[::-1]:  # a photo turned by 90 degrees
            images[stem] = np.ascontiguousarray(np.rot90(images[stem], k=1))
            sizes[stem] = dataclasses.replace(v, working_wh=(int(ref[0]), int(ref[1])), turned=1)
    write_views(out, images)
    (out / SIZES_FILE).write_text(json.dumps({k: v.to_json() for k, v in sizes.items()}, indent=2) + "\n")
    resized = sorted(s for s, v in sizes.items() if v.input_wh != (v.working_wh[::-1] if v.turned else v.working_wh))
    turned = sorted(s for s, v in sizes.items() if v.turned)
    return InputsSummary(max_size=max_size, sizes=sizes, resized=resized, turned=turned or None).to_json()


def read_sizes(path: str | Path) -> dict[str, dict[str, tuple[int, int] | int | str | None]]:
    """`sizes.json` -> stem -> {"input": (W, H), "working": (W, H), "turned": quarter turns counter-clockwise
    from the photo to its working image (0 or 1; 0 where the file does not say), "file": the photo's file
    name in the input folder (None where the file does not say)}.

    Raises:
        InputError: missing or malformed file.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
        out = {stem: {k: (int(v[k][0]), int(v[k][1])) for k in ("input", "working")} for stem, v in raw.items()}
        for stem, v in raw.items():
            turned = v.get("turned", 0)
            if turned not in (0, 1) or isinstance(turned, bool):
                raise ValueError(f"view {stem!r}: turned must be 0 or 1, got {turned!r}")
            out[stem]["turned"] = turned
            file = v.get("file")
            if file is not None and (not isinstance(file, str) or not file or Path(file).name != file
                                     or Path(file).stem != stem):
                raise ValueError(f"view {stem!r}: file must be the name of its photo, got {file!r}")
            out[stem]["file"] = file
        return out
    except RecursionError:  # deeply nested JSON
        raise InputError("cannot read the working sizes (JSON nested too deeply)", path=path,
                         fix="re-run with --force to rebuild OUT/inputs") from None
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError) as exc:  # Attribute: a list
        raise InputError(f"cannot read the working sizes ({exc})", path=path,
                         fix="re-run with --force to rebuild OUT/inputs") from exc


def working_focal_prior(working_dir: str | Path):
    """The alignment's focal prior from the input photos' EXIF (`mvgeo.align.intrinsics.common_focal_prior`
    over `sizes.json`'s `focal_35mm`), or (None, why not). A `sizes.json` written before it recorded the
    EXIF focal gives none.

    Raises:
        InputError: a missing or malformed `sizes.json`.
    """
    from mvgeo.align.intrinsics import common_focal_prior

    path = Path(working_dir) / SIZES_FILE
    read_sizes(path)  # the same checks as every reader of the file
    raw = json.loads(path.read_text())
    stems = sorted(raw)
    values = []
    for k in stems:
        v = raw[k].get("focal_35mm")
        if v is not None and not (isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                                  and v > 0):
            raise InputError(f"view {k!r}: focal_35mm must be a positive number of millimetres or null, got {v!r}",
                             path=path, fix="re-run with --force to rebuild OUT/inputs")
        values.append(None if v is None else float(v))
    return common_focal_prior(values, stems)


#: What `working_dataset` copies of an evaluation dataset, downscaled or as it is (`depth/` where it exists).
_COPIED = ("images", "clean", "depth", "sparse/0", "split.json")


def _source_digest(folder: Path) -> str:
    """Hash of the files of `folder` that `working_dataset` copies: a changed source dataset at the same path
    is made again."""
    from eval.pipeline.hashing import hash_json, hash_path

    return hash_json({part: hash_path(folder / part) for part in _COPIED if (folder / part).exists()})


#: The code that makes a working-size dataset (`working_dataset`: the area filter, the PNG writing, the cameras'
#: scaling); its source digests are in the dataset's record, so a dataset made by other code is made again.
_DATASET_CODE = ("eval.pipeline", "mvgeo")


def _dataset_code() -> dict[str, str]:
    """`_DATASET_CODE` -> source digest (`eval.pipeline.hashing.source_digest`)."""
    from eval.pipeline.hashing import source_digest

    return {name: source_digest(name) for name in _DATASET_CODE}


def _recorded_dataset(data_dir: Path, name: str, source: Path, max_size: int, digest: str) -> bool:
    """`data_dir/name` is the complete working-size dataset its record says `working_dataset` made from
    `source` at `max_size` from the files of hash `digest` (`_source_digest`) with the code there is now
    (`_dataset_code`), every file as recorded."""
    try:
        rec = json.loads((data_dir / RECORD_DIR / f"{name}.json").read_text(encoding="utf-8"))
        return (isinstance(rec, dict) and not rec.get("pending") and rec.get("source") == str(source)
                and rec.get("source_digest") == digest and rec.get("code") == _dataset_code()
                and rec.get("max_size") == max_size and isinstance(rec.get("manifest"), dict)
                and verify_outputs(data_dir, rec["manifest"]) is None)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):  # RecursionError: deeply nested JSON
        return False


def nearest_depth(depth: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """(H', W') depth map at `size_wh`: each pixel takes the depth of the input pixel under its centre (a depth
    is a surface's, not a colour to average: an area filter would put points between a foreground edge and the
    background behind it; misses, inf, stay misses)."""
    H, W = depth.shape
    w, h = size_wh
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    return np.ascontiguousarray(depth[rows[:, None], cols[None, :]])


def working_dataset(folder: str | Path, out: str | Path, max_size: int | None) -> Path:
    """An evaluation dataset (`images/`, `clean/`, `split.json`, `sparse/0/`) at the working size.

    `folder` itself when no image's long side exceeds `max_size` (or `max_size` is None); else
    `out/data/<name>_max<N>/`, made once (reused while its record `out/data/stages/<name>_max<N>.json` says
    it is complete and unchanged, and was made by the code there is now: `_DATASET_CODE`): the noisy and
    clean images downscaled with the area filter (16-bit PNG), the ground-truth cameras scaled to match
    (`Camera.scaled`, poses unchanged), `split.json` copied, and `depth/` maps where the dataset has them
    (`nearest_depth`). Other files of `folder` are not copied; when
    those it copies change (`_source_digest`), it is made again. It is written in a hidden work folder and
    committed with the record (`eval.pipeline.stage.commit_written`), so only a folder this function made is
    ever replaced.

    Raises:
        InputError: an image whose size differs from its ground-truth camera's.
        UnownedOutputError: `out/data/<name>_max<N>/` exists and holds files this function did not write
            there, or that changed since (refused before anything is written; nothing is changed).
    """
    from mvgeo.sparse_model import SparseModel, read_sparse_model, write_sparse_model

    folder, out = Path(folder), Path(out)
    files = {part: view_files(folder / part) for part in ("images", "clean")}
    sizes = {}
    for part, views in files.items():
        for stem, path in views.items():
            img = read_image(path)
            sizes[part, stem] = (img.shape[1], img.shape[0])
    if max_size is None or all(max(s) <= max_size for s in sizes.values()):
        return folder
    data_dir, name = out / DATA_DIR, f"{folder.name}_max{max_size}"
    target, source, digest = data_dir / name, folder.resolve(), _source_digest(folder)
    if _recorded_dataset(data_dir, name, source, max_size, digest):
        return target
    gt = read_sparse_model(folder / "sparse" / "0")
    cameras = {}
    for im in gt.images:
        cam, stem = gt.cameras[im.camera_id], Path(im.name).stem
        for part in ("images", "clean"):
            if (part, stem) in sizes and sizes[part, stem] != (cam.width, cam.height):
                raise InputError(f"{part}/{stem} is {sizes[part, stem][0]}x{sizes[part, stem][1]} px but its "
                                 f"ground-truth camera is {cam.width}x{cam.height}", path=folder / part,
                                 fix="make the images and sparse/0 agree")
        cameras[im.camera_id] = cam.scaled(*working_size(cam.width, cam.height, max_size))

    def write(work: Path) -> None:
        tmp = work / name
        for part, views in files.items():
            write_views(tmp / part, {stem: resize_area(read_image(p), working_size(*sizes[part, stem], max_size))
                                     for stem, p in views.items()})
        write_sparse_model(tmp / "sparse" / "0", SparseModel(cameras, gt.images, gt.points_xyz, gt.points_rgb),
                           binary=False)
        (tmp / "split.json").write_bytes((folder / "split.json").read_bytes())
        if (folder / "depth").is_dir():  # data_synth's depth maps (the `3dgs_gt_poses` baseline's points)
            (tmp / "depth").mkdir()
            for f in sorted((folder / "depth").glob("*.npy")):
                wh = sizes.get(("clean", f.stem), sizes.get(("images", f.stem)))
                if wh is not None:
                    np.save(tmp / "depth" / f.name, nearest_depth(np.load(f, allow_pickle=False),
                                                                  working_size(*wh, max_size)))

    commit_written(data_dir, name, (name,), write, {"source": str(source), "source_digest": digest,
                                                   "max_size": max_size, "code": _dataset_code()})
    return target
