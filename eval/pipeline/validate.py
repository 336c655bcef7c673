"""Up-front input checks for `denoise-gs run` and `denoise-gs eval`, before any compute.

Everything a stage would reject hours later is rejected here with an
`InputError` that names the file and the fix (the CLI exits with code 2).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eval.pipeline.config import PipelineConfig
from eval.pipeline.inputs import reference_working_size, working_size
from eval.pipeline.views import view_files
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, upright_size
from mvgeo.common.jsonio import read_json_object

__all__ = ["MIN_IMAGE_SIZE_PX", "DatasetFolder", "check_intrinsics", "check_renderable_cameras",
           "validate_dataset_folder", "validate_run_inputs"]

#: Smallest image side accepted: LPIPS-AlexNet needs 31 px, alignment and the
#: 4-level UNet need more than a handful of pixels; 32 covers all.
MIN_IMAGE_SIZE_PX = 32
#: Pose-free alignment needs at least two views.
MIN_VIEWS = 2


def validate_run_inputs(images_dir: Path, config: PipelineConfig) -> dict[str, Path]:
    """Check the inputs of `run_pipeline`; return stem -> image file.

    Checks: the folder exists and holds images with distinct stems and no white space in their names (the
    run's COLMAP text cameras cannot hold it), each one
    decodes and is at least `MIN_IMAGE_SIZE_PX` on each side, no two hold the same pixels (a copy of a
    photo under another name carries no geometry; the alignment refuses identical images, but it sees the
    denoised photos, in which the denoiser has made the copies differ), all have one
    working size (after `config.max_size`: every stage, the alignment first,
    works on the working images and assumes one camera; inputs of different
    sizes that downscale to one size are accepted, and so are photos turned by
    90 degrees, except with a calibration: `prepare_inputs` turns them back), there are at
    least two, and at least `config.views` when a second round will select
    views (with fewer images than K the selection would be meaningless, so we
    stop and ask for a smaller `--views` instead of silently using all views),
    and a given calibration (`AlignSettings.intrinsics`) fits them (`check_intrinsics`).
    The output folder is checked before, by `mvgeo.common.output.prepare_output`.

    Raises:
        InputError: naming the offending file/option and the fix.
    """
    images_dir = Path(images_dir)
    files = view_files(images_dir)
    seen: list[tuple[Path, tuple[int, int], tuple[int, int]]] = []
    digests: dict[str, Path] = {}
    for path in files.values():
        if any(ch.isspace() for ch in path.name):
            # The run writes its cameras as COLMAP text models (`cameras/`), whose images.txt cannot hold a
            # name with white space: COLMAP and pycolmap read it back cut at the first space.
            raise InputError(f"the file name {path.name!r} holds white space, which the COLMAP cameras this "
                             "command writes cannot hold", path=path,
                             fix="rename the photos without spaces (e.g. replace them with _)")
        img = read_image(path)
        digest = hashlib.sha1(repr(img.shape).encode() + img.tobytes()).hexdigest()
        if digest in digests:
            raise InputError(f"images {digests[digest].name!r} and {path.name!r} hold the same pixels (a duplicate "
                             "view carries no geometry)", path=path, fix="remove one of them from the folder")
        digests[digest] = path
        if min(img.shape[:2]) < MIN_IMAGE_SIZE_PX:
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} px; at least {MIN_IMAGE_SIZE_PX} px per "
                             "side is needed", path=path, fix="use larger images")
        w, h = working_size(img.shape[1], img.shape[0], config.max_size)
        if min(w, h) < MIN_IMAGE_SIZE_PX:
            raise InputError(f"--max-size {config.max_size} makes this {img.shape[1]}x{img.shape[0]} image {w}x{h} "
                             f"px; at least {MIN_IMAGE_SIZE_PX} px per side is needed", path=path,
                             fix="pass a larger --max-size")
        seen.append((path, (img.shape[1], img.shape[0]), (w, h)))
    first = None
    if seen:
        ref = reference_working_size([v[2] for v in seen])
        first = next(v for v in seen if v[2] == ref)
        for view in seen:
            # A photo turned by 90 degrees is turned back to the common orientation (`prepare_inputs`); with
            # --intrinsics it is refused: one calibration, of one input size.
            if view[2] != ref and not (view[2] == ref[::-1] and config.align.intrinsics is None):
                raise InputError(_mixed_sizes(first, view, config.max_size), path=images_dir,
                                 fix=_mixed_sizes_fix(first[1], view[1]))
            if config.align.intrinsics is not None and view[1] != first[1]:  # one calibration: one input size
                raise InputError(f"images have different sizes ({first[0].name}: {first[1][0]}x{first[1][1]}, "
                                 f"{view[0].name}: {view[1][0]}x{view[1][1]}) but --intrinsics gives one camera",
                                 path=images_dir, fix="pass photos of one size, the size the calibration is for")
    if config.align.intrinsics is not None and first is not None:
        check_intrinsics(Path(config.align.intrinsics), first[1])
    n = len(files)
    if n < MIN_VIEWS:
        raise InputError(f"only {n} image(s); pose-free reconstruction needs at least {MIN_VIEWS}",
                         path=images_dir, fix="add more views of the scene")
    if config.rounds >= 2 and config.select_views and n < config.views:
        raise InputError(f"{n} images but --views {config.views}: round 2 keeps K = --views views chosen "
                         f"among the inputs, so K cannot exceed the number of images", path=images_dir,
                         fix=f"pass --views {n} (or fewer), or add images")
    return files


def check_intrinsics(path: Path, size_wh: tuple[int, int]) -> Camera:
    """The photos' calibration `path` (`AlignSettings.intrinsics`), checked for photos of input size `size_wh`.

    Raises:
        InputError: the file is missing or unreadable, holds several cameras, has lens distortion (the
            splat trains on the photos as they are: they must be undistorted first), or is for another size.
    """
    from mvgeo.align.intrinsics import read_intrinsics

    camera = read_intrinsics(path)
    if np.any(camera.dist != 0.0):
        raise InputError(f"the calibration has lens distortion ({camera.model}); the splat trains on the photos "
                         "as they are, so they must be undistorted", path=path,
                         fix="undistort the photos first (e.g. COLMAP's image_undistorter) and pass their PINHOLE "
                             "camera")
    if camera.size_wh != tuple(size_wh):
        raise InputError(f"the calibration is for {camera.width}x{camera.height} images, the photos are "
                         f"{size_wh[0]}x{size_wh[1]}", path=path,
                         fix="pass the calibration of these photos at their size")
    return camera


def _mixed_sizes_fix(a_wh: tuple[int, int], b_wh: tuple[int, int]) -> str:
    """The fix for two input sizes that differ. A portrait photo among landscape ones (or the reverse) is the
    same camera turned by 90 degrees: the run turns it back itself, except with --intrinsics (one calibration,
    of one input size), where the photos are to be rotated to one orientation first, not resized."""
    if a_wh == b_wh[::-1]:
        return ("one photo is portrait and the other landscape (the same camera turned by 90 degrees), and "
                "--intrinsics gives one camera: rotate the photos to the calibration's orientation first, without "
                "resizing")
    return "resize or crop all images to one size first (the alignment assumes one camera)"


def _mixed_sizes(a: tuple[Path, tuple[int, int], tuple[int, int]], b: tuple[Path, tuple[int, int], tuple[int, int]],
                 max_size: int | None) -> str:
    """The message for two images (file, input (W, H), working (W, H)) whose working sizes differ."""
    text = f"images have different sizes ({a[0].name}: {a[1][0]}x{a[1][1]}, {b[0].name}: {b[1][0]}x{b[1][1]})"
    if (a[1], b[1]) != (a[2], b[2]):
        text += f"; at --max-size {max_size} they are {a[2][0]}x{a[2][1]} and {b[2][0]}x{b[2][1]}"
    return text


@dataclass(frozen=True)
class DatasetFolder:
    """A checked evaluation dataset.

    Attributes:
        root: the folder.
        train: stems of the training views (the only noisy images a method sees).
        test: stems of the held-out views (scored against `clean/`).
        images: stem -> noisy image file; clean: stem -> clean image file.
    """

    root: Path
    train: list[str]
    test: list[str]
    images: dict[str, Path]
    clean: dict[str, Path]


def validate_dataset_folder(root: Path) -> DatasetFolder:
    """Check an evaluation dataset: `images/`, `clean/`, `split.json`, ground-truth `sparse/0/`.

    Raises:
        InputError: a part is missing or inconsistent (names the part and the fix).
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError("dataset folder does not exist", path=root,
                         fix="pass a data_synth scene name, a scene .toml, or a dataset folder")
    fix = "a dataset folder holds images/ (noisy), clean/, split.json and sparse/0/ (as `data-synth render` writes)"
    for part in ("images", "clean"):
        if not (root / part).is_dir():
            raise InputError(f"dataset has no {part}/ folder", path=root / part, fix=fix)
    split_path = root / "split.json"
    if not split_path.is_file():
        raise InputError("dataset has no split.json (train/test views)", path=split_path, fix=fix)
    if not (root / "sparse" / "0").is_dir():
        raise InputError("dataset has no ground-truth sparse/0/ cameras", path=root / "sparse" / "0", fix=fix)
    split_fix = 'write split.json as UTF-8 JSON {"train": ["NAME.png", ...], "test": ["NAME.png", ...]}'
    split = read_json_object(split_path, fix=split_fix)
    for key in ("train", "test"):
        names = split.get(key)
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise InputError(f"split.json's {key!r} must be a list of image names (strings), got {names!r:.80}",
                             path=split_path, fix=split_fix)
    images = view_files(root / "images")
    clean = view_files(root / "clean")
    train = [Path(n).stem for n in split["train"]]
    test = [Path(n).stem for n in split["test"]]
    if not train or not test:
        raise InputError(f"split.json needs training and held-out views (has {len(train)} train, "
                         f"{len(test)} test)", path=split_path, fix=split_fix)
    if set(train) & set(test):
        raise InputError(f"views {sorted(set(train) & set(test))} are both train and test", path=split_path,
                         fix="list each view under one of them: a held-out view must not be trained on")
    for name in train:
        if name not in images:
            raise InputError(f"training view {name!r} has no noisy image", path=root / "images",
                             fix=f"put {name} into images/, or take it out of split.json's train list")
    for name in test:
        if name not in clean:
            raise InputError(f"held-out view {name!r} has no clean image", path=root / "clean",
                             fix=f"put {name} into clean/ (the held-out views are scored against it), or take it "
                                 "out of split.json's test list")
        if name not in images:  # the target of the held-out pose fit (`eval.evaluate`): the clean one serves scoring
            raise InputError(f"held-out view {name!r} has no noisy image", path=root / "images",
                             fix=f"put {name} into images/ (the pose-free methods fit its camera to the noisy photo "
                                 "before it is scored), or take it out of split.json's test list")
    _one_orientation({n: images[n] for n in train}, root / "images")
    # clean/ of the training views too, where there is one: `oracle_clean` splats them
    _sizes_match_cameras(root, [images[n] for n in train] + [clean[n] for n in train + test if n in clean])
    return DatasetFolder(root, train, test, images, clean)


def _sizes_match_cameras(root: Path, files: list[Path]) -> None:
    """Refuse an image whose size is not its ground-truth camera's (`sparse/0`): the methods splat the noisy
    training photos with those cameras and score the held-out clean ones against renders of them, so a
    mismatch would fail after the training, or score the wrong pixels. Views the model lacks, and a model
    that cannot be read, are left to the steps that read the cameras."""
    from mvgeo.sparse_model import read_sparse_model

    try:
        model = read_sparse_model(root / "sparse" / "0")
    except InputError:  # no or no readable model: reported by the steps that read the cameras
        return
    by_stem = {Path(n).stem: n for n in model.names}
    for path in files:
        name = by_stem.get(path.stem)
        size = upright_size(path)
        if name is None or size is None:
            continue
        cam = model.camera_of(name)
        if size != (cam.width, cam.height):
            raise InputError(f"the image is {size[0]}x{size[1]} but its camera in sparse/0 is {cam.width}x"
                             f"{cam.height}", path=path,
                             fix="give every image of images/ and clean/ its camera's size (re-import or "
                                 "re-render the dataset)")


def check_renderable_cameras(dataset: DatasetFolder) -> None:
    """Refuse ground-truth cameras (`sparse/0`) of the dataset's views that the splat cannot render: lens
    distortion, or a focal length that is not positive (`Camera.pinhole_problem`). For the methods that splat
    with the true cameras (`ground_truth_poses`, the `@gt_poses` variants), which would otherwise fail after
    their training; the other methods render with their own pinhole cameras. A model that cannot be read is
    left to the steps that read it.

    Raises:
        InputError: naming sparse/0, the camera and the fix.
    """
    from mvgeo.sparse_model import read_sparse_model

    try:
        model = read_sparse_model(dataset.root / "sparse" / "0")
    except InputError:
        return
    views = set(dataset.train) | set(dataset.test)
    used = {im.camera_id for im in model.images if Path(im.name).stem in views}
    for camera_id in sorted(used):
        problem = model.cameras[camera_id].pinhole_problem()
        if problem is not None:
            raise InputError(f"camera {camera_id} of the ground-truth cameras cannot be rendered: {problem}",
                             path=dataset.root / "sparse" / "0",
                             fix="undistort the images and the model first (COLMAP's image_undistorter) and "
                                 "import the undistorted ones, or leave out the methods that splat with the "
                                 "true cameras (3dgs_gt_poses, the @gt_poses variants)")


def _one_orientation(files: dict[str, Path], folder: Path) -> None:
    """Refuse an evaluation dataset whose training photos are of two orientations (W x H and H x W).
    `denoise-gs run` turns such photos to one orientation (`prepare_inputs`), but an evaluation scores the
    poses and the splat in each photo's own frame, which that would turn by 90 degrees."""
    first: dict[tuple[int, int], str] = {}
    for n, p in files.items():
        size = upright_size(p)
        if size is not None:
            first.setdefault(size, n)
    for sa, a in first.items():
        sb = sa[::-1]
        if sb != sa and sb in first:
            raise InputError(f"training views of two orientations ({a}: {sa[0]}x{sa[1]}, {first[sb]}: "
                             f"{sb[0]}x{sb[1]}); an evaluation compares poses in each photo's own frame", path=folder,
                             fix="import the views of one orientation only (a run, `denoise-gs run`, takes both)")
