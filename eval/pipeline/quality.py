"""What a pipeline run can say about its own result without ground truth: the report's "Quality" section.

A user's photos come without clean images or true cameras, so the run's self-checks are all there is:
how well the denoiser's training converged and which objective it chose; how many views the alignment
registered, where its focal length came from and how well it is determined, how far the bundle
adjustment's tracks reproject, how many pairs related the views and how many were rejected; how closely
the splat fits its own training photos. `round_quality` gathers these from a round's stage summaries and
`align.json` (`mvgeo.align.AlignStats`) into a typed `RoundQuality`; `quality_lines` writes them as
Markdown; `camera_plot_png` draws the cameras, seen from above and from behind, over the alignment's points.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eval.pipeline.rounds import RoundResult
from eval.pipeline.summaries import AlignSummary, DenoiseSummary, PhotoNoise, RefineSummary, SplatSummary
from eval.pipeline.views import view_files
from mvgeo.align.stats import AlignStats
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import SparseModel, read_sparse_model

__all__ = ["AlignQuality", "DenoiseQuality", "RoundQuality", "SplatQuality", "camera_plot_png", "noise_level_255",
           "plot_axes", "quality_lines", "round_quality"]

#: Points of the alignment's cloud drawn under the cameras (an even subsample).
PLOT_POINTS = 4000
#: Views listed as the least constrained (largest centre standard deviation of the bundle adjustment).
LEAST_CONSTRAINED = 3


@dataclass(frozen=True)
class DenoiseQuality:
    """Round 1's denoiser: its objective (None where the preset fixed it), the photos' dark and clipped
    fraction that chose it, and its training loss at the first and last step."""

    objective: str | None
    dark_clipped_fraction: float | None
    loss_first: float | None
    loss_last: float | None
    steps: int | None
    restarts: int = 0
    #: "training" (round 1's denoise stage) or "fine-tuning" (a later round's refine stage).
    kind: str = "training"
    #: round 1: each noisy photo's noise std (/255) as the default denoiser estimates it, recorded by the
    #: denoise stage (`noise_levels`); the median of the per-pixel map for the photos in `signal_dependent`
    #: (noise that grows with the intensity, e.g. shot noise).
    noise_std_255: dict[str, float] = field(default_factory=dict)
    signal_dependent: list[str] = field(default_factory=list)
    #: round 1: the pixel-shuffle stride the photos were denoised at (1: none; None: not recorded) and the
    #: noise level (/255) read on the photos and on their sub-images by stride that chose it
    #: (`denoise.pixel_shuffle.choose_stride`).
    pd_stride: int | None = None
    noise_level_by_stride_255: dict[str, float] = field(default_factory=dict)
    #: round 1: where the photos' noise is chroma-subsampled (a JPEG's), the level their luma reads (/255).
    noise_level_luma_255: float | None = None
    #: round 1: where no noise was found but the photos look like a camera's JPEGs, the level their stride-2
    #: sub-images' luma reads (/255): the report suggests `--pd-stride 2 --noise-model luma`.
    noise_level_luma_hint_255: float | None = None
    #: round 1: the photos read as clean and were passed through undenoised (no network trained).
    passed_through: bool = False


@dataclass(frozen=True)
class AlignQuality:
    """The alignment's self-checks (`AlignStats`; pixels at the alignment size).

    Attributes:
        photos: which photos were aligned ("noisy" or "denoised"; None where not recorded).
        photos_reason: why those, where round 1 aligned both (`AlignSettings.photos` "better_of"); else None.
        photos_identical: the denoised photos were the noisy ones (passed through), aligned once.
        focal_source: where the focal length came from, in words.
        focal_px: median focal length over the views (alignment pixels); focal_log_std: its standard
            deviation in log units from the bundle adjustment (0.01 = 1 %), NaN without one.
        least_constrained: up to `LEAST_CONSTRAINED` (view, centre std / median nearest-camera distance),
            largest first.
        pairs_unexplained: verified pairs the chosen poses do not explain (view, view, explained fraction).
    """

    n_registered: int
    n_images: int
    unregistered: list[tuple[str, str]]
    photos: str | None
    align_size_wh: list[int]
    focal_source: str
    focal_px: float
    focal_log_std: float
    reproj_rms_px: float
    reproj_median_px: float
    n_tracks: int
    n_observations: int
    n_pairs: int
    n_pairs_verified: int
    n_pairs_dense: int
    n_pairs_rejected_by_loops: int
    pairs_unexplained: list[tuple[str, str, float]]
    start: str
    n_candidates: int
    least_constrained: list[tuple[str, float]] = field(default_factory=list)
    photos_reason: str | None = None
    photos_identical: bool = False


@dataclass(frozen=True)
class SplatQuality:
    """The splat at the round's own views (not a held-out score): each view's render against the photo the
    splat trained on (the round's denoised photo, or its fused one with the fuse extension; PSNR, dB: a view
    the scene reproduces much worse than the others has a pose or content the scene does not explain),
    Gaussians at the end, optimisation seconds.

    Attributes:
        fit_psnr_db: view name -> PSNR of its render against its training photo.
    """

    fit_psnr_db: dict[str, float]
    n_gaussians: int | None
    seconds: float | None

    @property
    def worst(self) -> list[tuple[str, float]]:
        """Up to `LEAST_CONSTRAINED` views with the lowest PSNR, lowest first."""
        return sorted(self.fit_psnr_db.items(), key=lambda kv: kv[1])[:LEAST_CONSTRAINED]


@dataclass(frozen=True)
class RoundQuality:
    """One round's self-checks (None: the stage did not run in this round or recorded nothing)."""

    index: int
    denoise: DenoiseQuality | None
    align: AlignQuality | None
    splat: SplatQuality | None

    def to_json(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self), allow_nan=True))


def noise_level_255(sigma: object) -> float:
    """One photo's noise level /255 from its `r2r_noise_std` estimate: the number, or a per-pixel map's median
    (noise that grows with the intensity)."""
    return 255.0 * float(sigma.median() if hasattr(sigma, "median") else sigma)


def noise_levels(images: Mapping[str, np.ndarray], stds: Sequence[object] | None = None) -> PhotoNoise:
    """The denoise stage's record of its photos' noise: each view's std /255 and the views whose noise grows
    with the intensity, as the default denoiser estimates it (`r2r_noise_std`; a per-pixel map's median).
    `stds`: those estimates, one per image in order, where the caller has them already (default: estimated
    here)."""
    import torch

    from denoise.self_supervised import r2r_noise_std

    if stds is None:
        stds = [r2r_noise_std(img) for img in images.values()]
    if len(stds) != len(images):
        raise ValueError(f"{len(stds)} noise estimates for {len(images)} images")
    levels = {name: noise_level_255(sigma) for name, sigma in zip(images, stds, strict=True)}
    dependent = [name for name, sigma in zip(images, stds, strict=True) if isinstance(sigma, torch.Tensor)]
    return PhotoNoise(levels, dependent)


def _denoise_quality(summary: DenoiseSummary) -> DenoiseQuality:
    """Round 1's denoiser from its stage's summary."""
    loss, noise = summary.loss, summary.noise or PhotoNoise()
    return DenoiseQuality(objective=summary.objective, dark_clipped_fraction=summary.dark_clipped_fraction,
                          loss_first=None if loss is None else loss.first,
                          loss_last=None if loss is None else loss.last,
                          steps=None if loss is None else loss.count,
                          restarts=len(summary.training_restarts), kind="training",
                          noise_std_255=dict(noise.noise_std_255), signal_dependent=list(noise.signal_dependent),
                          pd_stride=summary.pd_stride,
                          noise_level_by_stride_255=dict(summary.noise_level_by_stride_255 or {}),
                          noise_level_luma_255=summary.noise_level_luma_255,
                          noise_level_luma_hint_255=summary.noise_level_luma_hint_255,
                          passed_through=bool(summary.passed_through))


def _fine_tuning_quality(summary: RefineSummary) -> DenoiseQuality:
    """A later round's fine-tuning from its refine stage's summary (no objective choice or noise record)."""
    loss = summary.loss
    return DenoiseQuality(objective=None, dark_clipped_fraction=None,
                          loss_first=None if loss is None else loss.first,
                          loss_last=None if loss is None else loss.last,
                          steps=None if loss is None else loss.count, kind="fine-tuning", pd_stride=summary.pd_stride)


def _focal_source(stats: AlignStats) -> str:
    if stats.known_intrinsics:
        return "given (the calibration passed with --intrinsics)"
    if stats.focal_prior is not None:
        return (f"started at the photos' {stats.focal_prior.source} focal ({stats.focal_prior.focal_35mm:g} mm "
                "equivalent), refined by the bundle adjustment")
    if stats.focal_determined_by_pairs:
        return "estimated from the pairs, refined by the bundle adjustment"
    return "not determined by any pair: started at the generic prior, set by the bundle adjustment"


def _align_quality(stats: AlignStats, summary: AlignSummary) -> AlignQuality:
    ba = stats.bundle_adjustment
    nan = float("nan")
    focals = [f for f in stats.focal_px.values() if f is not None and math.isfinite(f)]
    least: list[tuple[str, float]] = []
    if ba is not None and ba.centre_std_ratio and ba.views and len(ba.centre_std_ratio) == len(ba.views):
        order = np.argsort(ba.centre_std_ratio, kind="stable")[::-1][:LEAST_CONSTRAINED]
        least = [(ba.views[i], float(ba.centre_std_ratio[i])) for i in order]
    photos = summary.photos
    return AlignQuality(
        n_registered=stats.n_registered, n_images=stats.n_images,
        unregistered=[(u.name, u.reason) for u in stats.unregistered],
        photos=photos.aligned if photos is not None else None,
        photos_reason=photos.comparison.reason if photos is not None and photos.comparison is not None else None,
        photos_identical=photos is not None and photos.identical,
        align_size_wh=list(stats.align_size_wh), focal_source=_focal_source(stats),
        focal_px=float(np.median(focals)) if focals else nan,
        focal_log_std=ba.focal_log_std if ba is not None and not stats.known_intrinsics else nan,
        reproj_rms_px=ba.reproj_rms_after_px if ba is not None else nan,
        reproj_median_px=ba.reproj_median_after_px if ba is not None else nan,
        n_tracks=ba.n_points if ba is not None else 0, n_observations=ba.n_observations if ba is not None else 0,
        n_pairs=stats.n_pairs, n_pairs_verified=stats.n_pairs_verified, n_pairs_dense=stats.n_pairs_ok,
        n_pairs_rejected_by_loops=len(stats.pairs_rejected_by_loops),
        pairs_unexplained=[(p.i, p.j, p.explained_fraction) for p in stats.pairs_inconsistent],
        start=stats.initial_poses, n_candidates=len(stats.candidates), least_constrained=least)


def _views(folder: Path) -> dict[str, Path]:
    try:
        return view_files(folder)
    except InputError:
        return {}


def fit_psnr_db(renders_dir: Path, photos_dir: Path) -> dict[str, float]:
    """PSNR (dB, peak 1) of every render in `renders_dir` against the photo of the same name in `photos_dir`
    (views missing from either, or of another size, are left out; identical images give inf)."""
    photos = _views(photos_dir)
    out = {}
    for name, path in _views(renders_dir).items():
        if name in photos:
            a, b = read_image(path), read_image(photos[name])
            if a.shape == b.shape:
                mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
                out[name] = float("inf") if mse == 0 else -10.0 * math.log10(mse)
    return out


def _splat_quality(summary: SplatSummary, rd: Path, photos: str) -> SplatQuality:
    return SplatQuality(fit_psnr_db=fit_psnr_db(rd / "renders", rd / photos), n_gaussians=summary.num_gaussians,
                        seconds=summary.optimize_s)


def _align_json(rnd: RoundResult) -> Path | None:
    res = rnd.stages.get("align")
    if res is None:
        return None
    for path in res.outputs.values():
        if (Path(path) / "align.json").is_file():
            return Path(path) / "align.json"
    return None


def round_quality(rnd: RoundResult) -> RoundQuality:
    """The self-checks of round `rnd` from its stages' summaries (`eval.pipeline.summaries`) and its
    `align.json`.

    Raises:
        InputError: the round's align.json cannot be read.
    """
    denoise = None
    if "denoise" in rnd.stages:
        denoise = _denoise_quality(DenoiseSummary.from_json(rnd.stages["denoise"].summary))
    elif "refine" in rnd.stages:
        denoise = _fine_tuning_quality(RefineSummary.from_json(rnd.stages["refine"].summary))
    align_json = _align_json(rnd)
    align = None
    if align_json is not None:
        try:
            stats = AlignStats.read(align_json)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"cannot read the alignment's report: {exc}", path=align_json,
                             fix="run again with --force to recompute the round's alignment") from exc
        align = _align_quality(stats, AlignSummary.from_json(rnd.stages["align"].summary))
    splat = rnd.stages.get("splat")
    return RoundQuality(index=rnd.index, denoise=denoise, align=align,
                        splat=_splat_quality(SplatSummary.from_json(splat.summary), rnd.dir,
                                             "fused" if "fuse" in rnd.stages else "denoised")
                        if splat is not None else None)


def _fmt(x: float | None, spec: str) -> str:
    return "n/a" if x is None or not math.isfinite(x) else format(x, spec)


def quality_lines(rounds: Sequence[RoundQuality]) -> list[str]:
    """The report's Markdown section: one list per round."""
    lines = ["## Quality (the run's own checks; no ground truth)", ""]
    for q in rounds:
        lines += [f"### Round {q.index}", ""]
        d = q.denoise
        if d is not None and d.loss_last is not None:
            what = f"objective {d.objective}" if d.objective else "the preset's objective"
            why = (f" ({100 * d.dark_clipped_fraction:.1f} % of the photos' area dark and clipped)"
                   if d.dark_clipped_fraction is not None else "")
            restarts = f"; restarted {d.restarts} time(s) after diverging" if d.restarts else ""
            lines.append(f"- denoising: {what}{why}; {d.kind} loss {_fmt(d.loss_first, '.4g')} -> "
                         f"{_fmt(d.loss_last, '.4g')} over {d.steps} steps{restarts}")
        if d is not None and d.passed_through:
            lines.append("- denoising: **none: every photo's noise level read under the pass-through level "
                         "(`--pass-clean-below`), so the photos were used as they are and no network was trained**")
        if d is not None and d.noise_std_255:
            v = np.array(list(d.noise_std_255.values()))
            dep = (f"; signal-dependent (e.g. shot noise) in {len(d.signal_dependent)} of them: the median of "
                   "each one's per-pixel level" if d.signal_dependent else "")
            lines.append(f"- noise level of the {len(v)} photos as the denoiser estimates it: median "
                         f"{np.median(v):.1f}/255 (from {v.min():.1f} to {v.max():.1f}){dep}")
        if d is not None and d.pd_stride is not None and d.pd_stride > 1:
            read = ", ".join(f"{v:.1f}/255 at stride {k}" for k, v in d.noise_level_by_stride_255.items())
            lines.append(f"- the noise is correlated between neighbouring pixels, as a camera's demosaicing leaves it"
                         f"{f' (its level read on the photos and their sub-images: {read})' if read else ''}: the "
                         f"photos were denoised as {d.pd_stride} x {d.pd_stride} pixel-shuffled sub-images")
        if d is not None and d.noise_level_luma_255 is not None:
            colour = d.noise_level_by_stride_255.get("1")
            lines.append("- the photos' colour differences hold no fine noise, as a JPEG's 4:2:0 chroma subsampling "
                         f"leaves them{f' (their colour patches read {colour:.1f}/255)' if colour is not None else ''}"
                         f": the noise level was read on their luma, {d.noise_level_luma_255:.1f}/255"
                         f"{' (on the sub-images)' if d.pd_stride is not None and d.pd_stride > 1 else ''}")
        if d is not None and d.noise_level_luma_hint_255 is not None:
            from denoise.pixel_shuffle import luma_hint_text

            given = d.pd_stride if "1" not in d.noise_level_by_stride_255 else None  # a stride the user gave
            colour = d.noise_level_by_stride_255.get("1" if given is None else str(given), float("nan"))
            lines.append(f"- **{luma_hint_text(colour, d.noise_level_luma_hint_255, given_stride=given)}**")
        a = q.align
        if a is not None:
            photos = " (the photos, undenoised)" if a.photos_identical else f" ({a.photos} photos)" if a.photos else ""
            lines.append(f"- alignment{photos}: **{a.n_registered} of {a.n_images} views registered**" +
                         "".join(f"; `{n}` left out: {why}" for n, why in a.unregistered))
            if a.photos_reason:
                lines.append(f"  - of the noisy and the denoised photos' alignments, {a.photos_reason}")
            if a.photos_identical:
                lines.append("  - the denoised photos are the noisy ones (passed through undenoised): aligned once")
            std = (f", log-std {_fmt(a.focal_log_std, '.3f')} ({_fmt(100 * a.focal_log_std, '.1f')} %)"
                   if math.isfinite(a.focal_log_std) else "")
            w, h = a.align_size_wh
            lines.append(f"  - focal length {_fmt(a.focal_px, '.1f')} px at {w}x{h}{std}: {a.focal_source}")
            lines.append(f"  - bundle adjustment: {a.n_tracks} tracks, {a.n_observations} observations, "
                         f"reprojection error RMS {_fmt(a.reproj_rms_px, '.3f')} px, median "
                         f"{_fmt(a.reproj_median_px, '.3f')} px")
            lines.append(f"  - pairs: {a.n_pairs_verified} of {a.n_pairs} verified, {a.n_pairs_rejected_by_loops} "
                         f"rejected by the loop check, {a.n_pairs_dense} dense; start `{a.start}`, "
                         f"{a.n_candidates} candidate solution(s)")
            if a.pairs_unexplained:
                lines.append("  - verified pairs the poses do not fully explain: " + ", ".join(
                    f"`{i}`-`{j}` ({100 * f:.0f} % of its matches)" for i, j, f in a.pairs_unexplained))
            if a.least_constrained:
                lines.append("  - least constrained camera centres (std / distance to the nearest camera): " +
                             ", ".join(f"`{n}` {100 * r:.2f} %" for n, r in a.least_constrained))
        s = q.splat
        if s is not None:
            gauss = f"{s.n_gaussians} Gaussians" if s.n_gaussians is not None else "trained"
            secs = f" in {s.seconds:.0f} s" if s.seconds is not None else ""
            lines.append(f"- splat: {gauss}{secs}")
            if s.fit_psnr_db:
                med = float(np.median(list(s.fit_psnr_db.values())))
                lines.append(f"  - its renders of the {len(s.fit_psnr_db)} views against the photos it trained on "
                             f"(a fit, not a held-out score): median PSNR {_fmt(med, '.2f')} dB; lowest " +
                             ", ".join(f"`{n}` {_fmt(v, '.2f')} dB" for n, v in s.worst))
        lines.append("")
    return lines


def plot_axes(cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(forward, right, up) unit vectors of the plot: `up` against the cameras' mean image-down axis
    (OpenCV: +y is down), `forward` the mean viewing direction made orthogonal to it.

    Args:
        cam_from_world: (N, 3, 4).
    """
    R = np.asarray(cam_from_world, np.float64)[:, :, :3]
    up = -R[:, 1, :].mean(axis=0)  # row 1 of R is the camera's y axis in world coordinates
    up /= max(np.linalg.norm(up), 1e-12)
    fwd = R[:, 2, :].mean(axis=0)
    fwd -= up * (fwd @ up)
    if np.linalg.norm(fwd) < 1e-6:  # every camera looks straight up or down: any horizontal axis
        fwd = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    return fwd, np.cross(fwd, up), up


def camera_plot_png(path: Path, sparse: SparseModel, points_xyz: np.ndarray | None, *, title: str) -> Path:
    """Write a PNG of the cameras seen from above and from behind (`plot_axes`) over the alignment's points, and
    of the cameras alone from above (where a scene's extent would shrink them to a dot).

    Args:
        path: the PNG to write.
        sparse: the cameras (`cam_from_world` per image).
        points_xyz: (P, 3) points, or None.
        title: the figure's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sparse.names
    cfw = np.stack([sparse.image(n).cam_from_world for n in names])
    fwd, right, up = plot_axes(cfw)
    centres = np.stack([sparse.image(n).centre_world for n in names])
    dirs = cfw[:, 2, :3]
    spread = np.linalg.norm(centres - centres.mean(axis=0), axis=1)
    arrow = 0.25 * float(np.median(spread)) if len(names) > 1 and np.median(spread) > 0 else 1.0
    fig, axes = plt.subplots(1, 3, figsize=(15, 5))
    panels = [(right, fwd, "right", "forward", "from above"),
              (right, up, "right", "up", "from behind, along the mean viewing direction"),
              (right, fwd, "right", "forward", "the cameras alone, from above")]
    for k, (ax, (a, b, xl, yl, panel_title)) in enumerate(zip(axes, panels, strict=True)):
        if points_xyz is not None and len(points_xyz) and k < 2:
            step = max(1, len(points_xyz) // PLOT_POINTS)
            p = np.asarray(points_xyz, np.float64)[::step]
            u, v = p @ a, p @ b
            lo_u, hi_u = np.percentile(u, [2, 98])
            lo_v, hi_v = np.percentile(v, [2, 98])
            keep = (u >= lo_u) & (u <= hi_u) & (v >= lo_v) & (v <= hi_v)
            ax.scatter(u[keep], v[keep], s=1, c="0.7", linewidths=0)
        cu, cv = centres @ a, centres @ b
        ax.quiver(cu, cv, dirs @ a * arrow, dirs @ b * arrow, angles="xy", scale_units="xy", scale=1,
                  color="tab:red", width=0.004)
        ax.scatter(cu, cv, s=12, c="tab:red")
        if k == 2:  # named where the cameras are not a dot beside the scene
            for n, x, y in zip(names, cu, cv, strict=True):
                ax.annotate(Path(n).stem, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set(xlabel=xl, ylabel=yl, title=panel_title)
        ax.set_aspect("equal", adjustable="datalim")  # one scale on both axes, every panel the same size
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def round_camera_plot(dest: Path, rnd: RoundResult) -> Path | None:
    """`dest/report_files/cameras_round<N>.png` of round `rnd`: the splat's refined cameras (the
    alignment's where the round has no splat) over the alignment's points; None without cameras."""
    models = [Path(p) / "0" for name in ("splat",) if name in rnd.stages
              for p in [rnd.stages[name].outputs.get("sparse")] if p is not None]
    align_dir = next((Path(p) for p in rnd.stages["align"].outputs.values()), None) if "align" in rnd.stages else None
    if align_dir is not None:
        models.append(align_dir / "sparse" / "0")
    sparse = None
    for m in models:
        try:
            sparse = read_sparse_model(m)
            break
        except InputError:
            continue
    if sparse is None or not sparse.names:
        return None
    pts = None
    if align_dir is not None and (align_dir / "points.npz").is_file():
        with np.load(align_dir / "points.npz") as z:
            pts = np.asarray(z["xyz"], np.float64)
    return camera_plot_png(dest / "report_files" / f"cameras_round{rnd.index}.png", sparse, pts,
                           title=f"round {rnd.index}: {len(sparse.names)} cameras (red: centre and viewing "
                                 "direction) over the alignment's points")
