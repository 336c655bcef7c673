"""The product's fuse stage (`fuse`, `PipelineConfig.fuse_noisy_splat`): the denoised photos averaged with
renders of a splat trained on the noisy photos (`fuse_images`, `FUSE_WEIGHT`), and the check that lets a
round >= 2 reuse the previous round's noisy-photo renders (`noisy_splat_reuse`)."""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eval.pipeline.align_decisions import AlignDecisions
from eval.pipeline.hashing import file_sha256
from eval.pipeline.splat_training import train_splat
from eval.pipeline.stage import StageContext
from eval.pipeline.summaries import FuseSummary, RecordedGeometryChoice
from eval.pipeline.views import read_views, view_files, write_views
from mvgeo.sparse_model import read_sparse_model

__all__ = ["FUSE_WEIGHT", "ROTATION_ATOL", "NoisySplatReuse", "fuse", "fuse_images", "noisy_splat_reuse"]


#: Weight of the noisy photos' render in `fuse` (the denoised photo gets 1 - FUSE_WEIGHT): the plain mean
#: of two estimates of comparable quality (on `llff_like` 24.1 and 24.3 dB against the clean training
#: views), fixed a priori, not fitted to a scene.
FUSE_WEIGHT = 0.5


def fuse_images(denoised: np.ndarray, render: np.ndarray, weight: float = FUSE_WEIGHT) -> np.ndarray:
    """(1 - weight) * denoised + weight * render, both (H, W, 3) float in [0, 1]."""
    if denoised.shape != render.shape:
        raise ValueError(f"fuse: denoised {denoised.shape} and render {render.shape} differ in shape")
    return ((1.0 - weight) * denoised + weight * render).astype(np.float32)


#: Largest difference between rotation-matrix entries of two cam_from_world that `noisy_splat_reuse`
#: treats as the same pose. A handed-over pose goes through COLMAP's binary format once more, whose
#: quaternion round trip changes entries by up to ~1e-15 (translations, intrinsics and points are stored
#: as float64 and come back bit-exact); any re-estimated pose differs by many orders of magnitude more.
ROTATION_ATOL = 1e-12


@dataclass(frozen=True)
class NoisySplatReuse:
    """Whether a round's fuse stage takes the previous round's noisy-photo renders (`noisy_splat_reuse`).

    Attributes:
        reused: True: the previous round's renders of `views` are this round's.
        reason: the check that decided, in words.
    """

    reused: bool
    reason: str


def _same_camera(a, b) -> bool:
    return a.model == b.model and (a.width, a.height) == (b.width, b.height) and np.array_equal(a.params, b.params)


def _same_pose(cam_from_world_a: np.ndarray, cam_from_world_b: np.ndarray) -> bool:
    """(3, 4) cam_from_world each; equal translations, rotations within `ROTATION_ATOL`."""
    a, b = np.asarray(cam_from_world_a, np.float64), np.asarray(cam_from_world_b, np.float64)
    return bool(np.array_equal(a[:, 3], b[:, 3]) and np.abs(a[:, :3] - b[:, :3]).max() <= ROTATION_ATOL)


def noisy_splat_reuse(views: Sequence[str], *, align_dir: Path, previous_align_dir: Path, noisy_dir: Path,
                      previous_noisy_dir: Path, previous_renders_dir: Path) -> NoisySplatReuse:
    """Whether the previous round's noisy-photo splat was trained from what this round's would be.

    The previous round's fuse stage trained its splat on the noisy photos in `previous_noisy_dir` from
    the alignment in `previous_align_dir` and rendered every view into `previous_renders_dir`. This
    round's would train on `views` of `noisy_dir` from `align_dir`. Reuse needs: a previous render of
    every view; the same noisy image files (sha256); every view's camera and cam_from_world in this
    round's alignment equal to the previous round's (`_same_camera`, `_same_pose`); the same initial
    points (points.npz `xyz` and `rgb`). The previous splat then started from the same cameras and
    points and saw these views plus the previous round's others; its training settings are the
    run's (`PipelineConfig.splat`), the same in every round but for the seed.

    Args:
        views: this round's view stems.
        align_dir, previous_align_dir: align stage folders (`sparse/0/`, `points.npz`).
        noisy_dir, previous_noisy_dir: the noisy photos each round's fuse stage reads.
        previous_renders_dir: the previous round's `noisy_renders/`.
    """
    renders = view_files(previous_renders_dir)
    missing = [v for v in views if v not in renders]
    if missing:
        return NoisySplatReuse(False, f"the previous round has no noisy-photo render of {missing}")
    noisy, previous_noisy = view_files(noisy_dir), view_files(previous_noisy_dir)
    for v in views:
        if v not in noisy or v not in previous_noisy or file_sha256(noisy[v]) != file_sha256(previous_noisy[v]):
            return NoisySplatReuse(False, f"the noisy photo {v} differs from the previous round's")
    model = read_sparse_model(align_dir / "sparse" / "0")
    previous = read_sparse_model(previous_align_dir / "sparse" / "0")
    by_stem = {n.rsplit(".", 1)[0]: n for n in model.names}
    previous_by_stem = {n.rsplit(".", 1)[0]: n for n in previous.names}
    for v in views:
        if v not in by_stem or v not in previous_by_stem:
            return NoisySplatReuse(False, f"view {v} is not registered in both alignments")
        n, pn = by_stem[v], previous_by_stem[v]
        if not _same_camera(model.camera_of(n), previous.camera_of(pn)):
            return NoisySplatReuse(False, f"the intrinsics of {v} differ from the previous round's")
        if not _same_pose(model.image(n).cam_from_world, previous.image(pn).cam_from_world):
            return NoisySplatReuse(False, f"the cam_from_world of {v} differs from the previous round's")
    pts, previous_pts = np.load(align_dir / "points.npz"), np.load(previous_align_dir / "points.npz")
    if not all(np.array_equal(pts[k], previous_pts[k]) for k in ("xyz", "rgb")):
        return NoisySplatReuse(False, "the alignment's points differ from the previous round's")
    return NoisySplatReuse(True, "the same noisy photos, cameras, poses and points as the previous round's splat")


def _recorded_geometry_choice(align_dir: Path) -> RecordedGeometryChoice | None:
    """The align stage's rounds >= 2 decision in `align_dir`'s align.json (`AlignDecisions.geometry`) as
    the fuse stage's summary records it (used_previous, reason); None without one."""
    stats_file = align_dir / "align.json"
    if not stats_file.is_file():
        return None
    choice = AlignDecisions.read(stats_file).geometry
    if choice is None:
        return None
    return RecordedGeometryChoice(choice.used_previous, choice.reason)


def fuse(ctx: StageContext) -> Mapping[str, object]:
    """Extension (`PipelineConfig.fuse_noisy_splat`): the round's denoised photos averaged with renders,
    at their own (optimised) poses, of a splat trained on the *noisy* photos with the round's alignment.

    The splat of 12 noisy views keeps the scene's fine texture (the same in every view) and averages
    the noise (different in every view); the denoiser removes noise and texture alike. Their errors
    differ, so the mean is better than either (CHANGELOG.md, 2026-11-22). `ctx.settings`: a
    `FuseStageSettings`.

    Rounds >= 2 with `reuse_noisy_splat` (the runner then passes `previous_align`, `previous_noisy` and
    `previous_noisy_renders`): when `noisy_splat_reuse` finds the previous round's splat trained from
    the same noisy photos, cameras, poses and points, its renders of this round's views are copied
    (same bytes) instead of training a new splat on a subset of the same photos. The summary (a
    `FuseSummary`'s JSON) says which (`noisy_splat`: "reused" or "trained") and why (`noisy_splat_reason`).
    """
    s = ctx.settings
    # The alignment's registered views, in its order (those the splat trains on).
    stems = [n.rsplit(".", 1)[0] for n in read_sparse_model(ctx.inputs["align"] / "sparse" / "0").names]
    previous = ctx.inputs.get("previous_noisy_renders")
    if not s.reuse_noisy_splat:
        decision = NoisySplatReuse(False, "reuse_noisy_splat is off" if s.reuse_noisy_splat is False
                                   else "round 1 has no previous round")
    elif previous is None:
        decision = NoisySplatReuse(False, "no previous round's noisy-photo renders were given")
    else:
        decision = noisy_splat_reuse(stems, align_dir=ctx.inputs["align"],
                                     previous_align_dir=ctx.inputs["previous_align"],
                                     noisy_dir=ctx.inputs["noisy"], previous_noisy_dir=ctx.inputs["previous_noisy"],
                                     previous_renders_dir=previous)
    out_renders = ctx.work_dir / "noisy_renders"
    if decision.reused:
        out_renders.mkdir(parents=True)
        files = view_files(previous)
        for v in stems:
            shutil.copyfile(files[v], out_renders / files[v].name)
        renders = read_views(out_renders, stems)
        timings: dict[str, float] = {}
    else:
        from splat.render import render_views

        res, sparse, stems, _ = train_splat(ctx.inputs["noisy"], ctx.inputs["align"], s)
        cameras = [sparse.camera_of(n) for n in sparse.names]
        cam_from_world = np.stack([np.asarray(m)[:3] for m in res.cam_from_world_optimized])
        renders = dict(zip(stems, render_views(res.model, cameras, cam_from_world), strict=True))
        write_views(out_renders, renders)
        timings = dict(res.timings_s)
    denoised = read_views(ctx.inputs["images"], stems)
    write_views(ctx.work_dir / "fused", {k: fuse_images(denoised[k], renders[k]) for k in stems})
    return FuseSummary(views=stems, weight=FUSE_WEIGHT, noisy_splat="reused" if decision.reused else "trained",
                       noisy_splat_reason=decision.reason,
                       align_geometry=_recorded_geometry_choice(ctx.inputs["align"]),
                       timings_s=timings or None).to_json()
