"""Real photographs: `mvgeo align` vs pycolmap incremental and global mapping, on identical image files.

Usage: `python benchmarks/bench_real.py [--data=DIR[,DIR...]] [--sets=temple,dtu_spread,dtu_cluster,data]
[--noise=clean,noisy] [--noise-seeds=N]
[--methods=ours,ours_noexif,ours_intr,ours_partial,ours_intr_partial,ours_chain,ours_averaged,incremental,global,
global_intr] [--out=NAME] [--exif]`
(writes docs/bench/NAME.md, default `real`; only the table and its header). `--noise-seeds=N` (default 6) runs
the noisy variant with noise seeds 0..N-1 and adds a table of the noisy rows per set and method over the seeds:
one draw of the noise moves the pose errors by more than the methods differ. `--exif` writes every image with
the EXIF 35 mm-equivalent focal length a camera would record for the set's calibration (camera photos carry
it; the shared sets' PNGs do not), which both `mvgeo align` and pycolmap read as their starting focal.

Sets (each on 12 training views, clean and with Gaussian noise sigma = 25/255 added, seeds 0..N-1, saved as 8-bit PNG):
- `temple`: ../shared/data/temple_sparse_ring (Middlebury, 640x480, calibrated `templeSR_par.txt`), 12 of its 16
  views spread around the ring (`eval.real.split.ring_split`, the import's `--layout ring`: the duplicate camera
  position is dropped, then repeatedly the view whose two ring neighbours are closest);
- `dtu_spread`: ../shared/data/dtu_scan24 (384x384, `cameras.npz`), the 12 views of
  `eval.datasets.spread_split(49, 12, 4)` (20-40 deg between neighbours);
- `dtu_cluster`: the same scan, the 12 training views of `eval.datasets.cluster_split` (about 11 deg apart);
- any dataset folder in the project's layout given with `--data` (`images/` or `clean/`, `split.json` with
  `train`, `sparse/0` with the reference cameras): its first 12 training views; `clean/` when present is the
  clean variant (and gets the noise added), else `images/` is used as it is.
Missing sets are named and skipped; with none, the script says so and exits 0.

Methods, alternated (the order rotates from one variant to the next), all in this one process:
`ours` = `mvgeo align` defaults without the final dense stereo (poses + sparse points: the product pycolmap's
mappers make); `ours_noexif` (`ours, EXIF off`) = the same with `AlignConfig.exif_focal` off (with `--exif`:
what the EXIF focal buys, in the same run); `ours --intrinsics` = the same with the known calibration (a COLMAP
cameras.txt written from the set's calibration, read by `mvgeo.align.intrinsics.read_intrinsics`);
`ours_partial` (`ours --allow-partial`) = the defaults with `AlignConfig.allow_partial`: where the pairs do not
connect every view, or the verdict would cut views off, the largest group is registered and the others are named
(the note column), as the mappers return partial models; `ours_chain` / `ours_averaged` (`ours --initial-poses
chain|averaged`) = the defaults with that start first (the other start still follows where the first contradicts
its pairs); `ours_intr_partial` (`ours --intrinsics --allow-partial`) = both; `pycolmap
incremental` and `pycolmap global` (`mvgeo.align.colmap_sfm.run_colmap`: CPU SIFT, exhaustive matching, one
SIMPLE_RADIAL camera); `global_intr` (`pycolmap global, known camera`) = the global mapper with the set's
calibration as a fixed PINHOLE camera (`ColmapConfig.known_pinhole`), the counterpart of `ours --intrinsics`.

Columns: registered / total; rotation error median and max over all pairs of registered views (relative
rotations, `mvgeo.metrics.compare_poses`: free of the gauge); translation-direction error median; ATE RMSE of
the camera centres after Sim(3) alignment divided by the scene scale (RMS distance of the reference centres to
their centroid); focal error (%); seconds; verified pairs (ours: pairs with a relative pose; pycolmap: two-view
geometries with at least 15 inliers in its database after exhaustive matching, counted in a separate, untimed
run of its feature extraction and matching); and the bundle adjustment's tracks (ours).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from _common import ROOT, cli_option, md_table, write_fragment

os.environ.setdefault("GLOG_minloglevel", "2")  # pycolmap's per-image log lines

from eval.real.split import ring_split
from mvgeo.align.api import AlignConfig, align_images  # imports cv2 before pycolmap
from mvgeo.align.colmap_sfm import ColmapConfig, run_colmap
from mvgeo.align.dense_stereo import DenseStereoConfig
from mvgeo.align.intrinsics import FULL_FRAME_DIAGONAL_MM, read_intrinsics
from mvgeo.camera import Camera
from mvgeo.common.imageio import list_images, read_image, write_image
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import SparseModel, read_sparse_model, write_sparse_model

SHARED = ROOT.parent / "shared" / "data"
TEMPLE = SHARED / "temple_sparse_ring"
DTU = SHARED / "dtu_scan24"
SIGMA_8BIT = 25.0
N_VIEWS = 12
#: Poses-only `mvgeo align` (what pycolmap's mappers return).
OURS = AlignConfig(dense_stereo=DenseStereoConfig(enabled=False))


@dataclass
class RealSet:
    """One benchmark set: clean image files, reference cameras, calibration.

    Attributes:
        name: table label.
        files: the 12 image files (clean, or as given).
        gt: {file name: cam_from_world (3, 4)} reference poses.
        K: (3, 3) calibration in our pixel convention (top-left pixel centre at 0.5).
        add_noise: whether the noisy variant adds noise (False: the files are noisy already).
    """

    name: str
    files: list[Path]
    gt: dict[str, np.ndarray]
    K: np.ndarray
    add_noise: bool = True


def temple_set() -> RealSet | None:
    if not (TEMPLE / "templeSR_par.txt").is_file():
        return None
    rows = [ln.split() for ln in (TEMPLE / "templeSR_par.txt").read_text().splitlines()[1:] if len(ln.split()) == 22]
    names = [r[0] for r in rows]
    vals = np.array([[float(x) for x in r[1:]] for r in rows])
    Ks, Rs, ts = vals[:, :9].reshape(-1, 3, 3), vals[:, 9:18].reshape(-1, 3, 3), vals[:, 18:21]
    centres = -np.einsum("nji,nj->ni", Rs, ts)
    pick, _ = ring_split(centres, N_VIEWS)  # the layout `denoise-gs dataset import --layout ring` writes
    K = np.median(Ks[pick], axis=0)
    K[0, 2] += 0.5  # Middlebury's projection uses OpenCV pixel centres (top-left at 0)
    K[1, 2] += 0.5
    gt = {names[v]: np.hstack([Rs[v], ts[v][:, None]]) for v in pick}
    imgs = TEMPLE if list(TEMPLE.glob("*.png")) else TEMPLE / "images"
    return RealSet("temple_sparse_ring", [imgs / names[v] for v in sorted(pick)], gt, K)


def dtu_set(layout: str) -> RealSet | None:
    if not (DTU / "cameras.npz").is_file():
        return None
    from eval.datasets import cluster_split, dtu_cameras, spread_split

    files = sorted((DTU / "images").glob("*.png"))
    cams = dtu_cameras(DTU / "cameras.npz", len(files))
    if layout == "spread":
        train, _ = spread_split(len(files), N_VIEWS, 4)
    else:
        train, _ = cluster_split(np.array([T[2, :3] for _, T in cams]), N_VIEWS, 4)
    K = np.median(np.stack([cams[v][0] for v in train]), axis=0)
    return RealSet(f"dtu_scan24 ({layout})", [files[v] for v in train],
                   {files[v].name: cams[v][1] for v in train}, K)


def dtu_for_script(doc: str | None) -> RealSet | None:
    """The DTU `cluster` set for a diagnosis script's `main`, or None when there is nothing to run: `-h` /
    `--help` (prints `doc`) or ../shared/data/dtu_scan24 missing (says so)."""
    if "-h" in sys.argv or "--help" in sys.argv:
        print(doc)
        return None
    s = dtu_set("cluster")
    if s is None:
        print("../shared/data/dtu_scan24 is missing: nothing to run")
    return s


def folder_set(folder: Path) -> RealSet | None:
    """A dataset in the project's layout (`images/`/`clean/`, `split.json`, `sparse/0`)."""
    if not (folder / "sparse" / "0").is_dir():
        print(f"note: {folder} has no sparse/0, skipped", file=sys.stderr)
        return None
    ref = read_sparse_model(folder / "sparse" / "0")
    clean = (folder / "clean").is_dir()
    src = folder / ("clean" if clean else "images")
    names = [p.name for p in list_images(src)]
    split = folder / "split.json"
    if split.is_file():
        names = [n for n in json.loads(split.read_text())["train"] if n in names]
    names = [n for n in names if n in ref.names][:N_VIEWS]
    gt = {n: g for n, g in ref.cam_from_world_by_name().items() if n in names}
    return RealSet(folder.name, [src / n for n in names], gt, ref.camera_of(names[0]).K, add_noise=clean)


def prepare(s: RealSet, work: Path, noisy: bool, seed: int = 0, exif_35mm: int | None = None) -> Path:
    """A folder with exactly the set's 12 image files (8-bit PNG; noisy: sigma 25/255 added with `seed`);
    with `exif_35mm`, the same pixels carry that EXIF FocalLengthIn35mmFilm (`exif_focal_35mm_of`)."""
    tag = (f"noisy{seed}" if noisy else "clean") + ("" if exif_35mm is None else f"_exif{exif_35mm}")
    out = work / f"{s.name.replace(' ', '_').replace('(', '').replace(')', '')}_{tag}"
    out.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for f in s.files:
        if noisy and s.add_noise:
            img = np.round(read_image(f) * 255.0) / 255.0
            write_image(out / f.name, np.clip(img + rng.normal(0.0, SIGMA_8BIT / 255.0, img.shape), 0.0, 1.0))
        else:
            shutil.copy(f, out / f.name)
        if exif_35mm is not None:
            from PIL import Image

            before = read_image(out / f.name)
            exif = Image.Exif()
            exif.get_ifd(0x8769)[0xA405] = int(exif_35mm)  # Exif IFD, FocalLengthIn35mmFilm
            with Image.open(out / f.name) as im:
                im.load()
                im.save(out / f.name, exif=exif.tobytes())
            if not np.array_equal(read_image(out / f.name), before):  # e.g. a JPEG re-encoded, 16 bits cut to 8
                raise SystemExit(f"--exif: re-saving {f.name} with Pillow changed its pixels; --exif needs 8-bit "
                                 "PNG images (the shared sets' are)")
    return out


def exif_focal_35mm_of(K: np.ndarray, wh: tuple[int, int]) -> int:
    """The FocalLengthIn35mmFilm a camera writes for calibration `K` at image size `wh`: the same diagonal
    field of view on a 36 x 24 mm frame, in whole millimetres (the tag is an integer)."""
    return int(round(float(K[0, 0]) * FULL_FRAME_DIAGONAL_MM / float(np.hypot(*wh))))


def write_cameras_txt(K: np.ndarray, wh: tuple[int, int], path: Path) -> Path:
    """One PINHOLE camera in COLMAP's text format (the `mvgeo align --intrinsics` input)."""
    path.mkdir(parents=True, exist_ok=True)
    cam = Camera("PINHOLE", wh[0], wh[1], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    write_sparse_model(path, SparseModel({1: cam}, []), binary=False)
    return path / "cameras.txt"


def scene_scale(gt: dict[str, np.ndarray]) -> float:
    C = np.stack([-T[:, :3].T @ T[:, 3] for T in gt.values()])
    return float(np.sqrt(np.mean(np.sum((C - C.mean(axis=0)) ** 2, axis=1))))


def metrics_row(label, method, est: dict, gt: dict, f_est: float, f_ref: float, sec: float, pairs="", tracks="",
                note=""):
    m = compare_poses(est, gt)
    rot = m.rotation_deg
    ate = m.ate.rmse / scene_scale(gt) if m.ate is not None else float("nan")
    return [label, method, f"{m.n_registered}/{m.n_ref}", m.median_rotation_deg,
            float(rot.max()) if rot.size else float("nan"), m.median_translation_deg, ate,
            abs(f_est / f_ref - 1) * 100, sec, pairs, tracks, note]


def failed_row(label, method, exc: Exception, sec: float, pairs=""):
    msg = f"failed: {type(exc).__name__}: {exc}".replace("|", "/").replace("\n", " ")
    return [label, method, "0/12", "", "", "", "", "", sec, pairs, "", msg[:220]]


#: (row label, method, {stage: seconds}) of one run that returned a model: `stage_table`'s input.
StageTimes = tuple[str, str, dict[str, float]]


def run_ours(label, method, folder: Path, gt, f_ref, intrinsics_txt: Path | None, config: AlignConfig,
             stages: list[StageTimes] | None = None):
    paths = [p for p in list_images(folder) if p.name in gt]
    t = time.perf_counter()
    try:
        intr = read_intrinsics(intrinsics_txt) if intrinsics_txt is not None else None
        res = align_images(paths, config, intrinsics=intr)
    except Exception as exc:  # report, keep benchmarking
        return failed_row(label, method, exc, time.perf_counter() - t)
    sec = time.perf_counter() - t
    st = res.stats
    if stages is not None:
        stages.append((label, method, {k: v for k, v in st.timings_s.items() if k != "total"}))
    f = float(np.median([c.fx for c in res.sparse_model.cameras.values()]))
    ba = st.bundle_adjustment
    note = [f"{st.initial_poses} start, {len(st.candidates)} candidate(s)"]
    if st.sensitive_features:
        note.append("sensitive SIFT")
    if st.pairs_rejected_by_loops:
        note.append(f"{len(st.pairs_rejected_by_loops)} pairs rejected by loops")
    for outcome in ("kept", "re-posed"):
        views = [v.name for v in st.views_located_by_points if v.outcome == outcome]
        if views:
            note.append(f"{outcome} by PnP: {', '.join(views)}")
    if st.pairs_dropped_as_inconsistent:
        note.append(f"{len(st.pairs_dropped_as_inconsistent)} pairs dropped")
    if st.unregistered:
        note.append("left out: " + ", ".join(f"{u.name} ({_short_reason(u.reason)})" for u in st.unregistered))
    if ba is not None:
        note.append(f"reproj {ba.reproj_rms_after_px:.2g} px")
    return metrics_row(label, method, res.sparse_model.cam_from_world_by_name(), gt, f, f_ref, sec,
                       f"{st.n_pairs_verified}/{st.n_pairs}", "" if ba is None else ba.n_points, "; ".join(note))


def _short_reason(reason: str) -> str:
    return ("not connected" if "not connected" in reason else "inconsistent pairs" if "inconsistent" in reason
            else "position undetermined" if "not determined" in reason else reason[:40])


def run_pycolmap(label, mapper: str, folder: Path, gt, f_ref, stages: list[StageTimes] | None = None, *,
                 known_pinhole: tuple[float, float, float, float] | None = None):
    names = sorted(gt)
    method = f"pycolmap {mapper}" + (", known camera" if known_pinhole is not None else "")
    t = time.perf_counter()
    try:
        col = run_colmap(folder, ColmapConfig(mapper=mapper, known_pinhole=known_pinhole), image_names=names)
    except Exception as exc:
        return failed_row(label, method, exc, time.perf_counter() - t)
    sec = time.perf_counter() - t
    if stages is not None:
        stages.append((label, method, {k: v for k, v in col.stats.timings_s.items() if k != "total"}))
    f = float(np.median([c.fx for c in col.sparse_model.cameras.values()]))
    return metrics_row(label, method, col.sparse_model.cam_from_world_by_name(), gt, f, f_ref, sec,
                       tracks=col.stats.n_points)


def colmap_verified_pairs(folder: Path, names: list[str], min_inliers: int = 15) -> int:
    """Image pairs with a verified two-view geometry after pycolmap's extraction and exhaustive matching."""
    from mvgeo.common.deps import pycolmap

    with tempfile.TemporaryDirectory(prefix="bench-real-db-") as tmp:
        db_path = Path(tmp) / "database.db"
        ext = pycolmap.FeatureExtractionOptions()
        ext.use_gpu = False
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        pycolmap.extract_features(db_path, folder, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(db_path, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(db_path)
        try:
            _, geoms = db.read_two_view_geometries()
            bad = {pycolmap.TwoViewGeometryConfiguration.UNDEFINED, pycolmap.TwoViewGeometryConfiguration.DEGENERATE}
            return sum(1 for g in geoms if g.config not in bad and len(g.inlier_matches) >= min_inliers)
        finally:
            db.close()


METHODS = ("ours", "ours_noexif", "ours_intr", "ours_partial", "ours_intr_partial", "ours_chain", "ours_averaged",
           "global", "global_intr", "incremental")
#: Without --methods: `ours_noexif` is `ours` on images without EXIF, so only asked for with --exif.
DEFAULT_METHODS = ("ours", "ours_intr", "global", "incremental")


def noise_seed_summary(rows: list[list], n_seeds: int) -> str:
    """Per set and method, the noisy rows of all noise seeds together: one draw of the noise moves the pose
    errors by more than the methods differ (DTU scan24 cluster, ours: median 0.33-0.63 deg over 6 seeds)."""
    groups: dict[tuple[str, str], list[list]] = {}
    for r in rows:
        if ", noisy" in r[0]:
            groups.setdefault((r[0].split(", noisy")[0], r[1]), []).append(r)
    ref_time = {k[0]: np.mean([r[8] for r in v]) for k, v in groups.items() if k[1] == "pycolmap global"}
    out = []
    for (name, method), rs in groups.items():
        full = [r for r in rs if r[3] != "" and r[2].split("/")[0] == r[2].split("/")[1]]  # every view registered
        posed = [r for r in rs if r[3] != ""]  # a model (for a partial one, the errors of its registered views)

        def mean(col, rows=posed):
            vals = [float(r[col]) for r in rows if r[col] != "" and np.isfinite(float(r[col]))]
            return float(np.mean(vals)) if vals else float("nan")

        t = float(np.mean([r[8] for r in rs]))
        views = float(np.mean([int(r[2].split("/")[0]) for r in rs]))
        out.append([name, method, f"{len(full)}/{len(rs)}", views,
                    float(np.median([float(r[3]) for r in posed])) if posed else float("nan"), mean(3), mean(4),
                    mean(6), t, t / ref_time[name] if name in ref_time else float("nan")])
    return (f"\nNoisy rows of all {n_seeds} noise seeds (0..{n_seeds - 1}) together, per set and method: "
            "`full` = seeds with every view registered; `views` = registered views, mean over the seeds; the "
            "error columns are over the seeds with a model, of its registered views (median and mean of the "
            "per-seed median rotation error, mean of the per-seed max and ATE); time over all seeds, and its "
            "ratio to pycolmap global's mean time in this run.\n\n"
            + md_table(["set (noisy)", "method", "full", "views", "rot med: median", "rot med: mean", "rot max: mean",
                        "ATE / scale: mean", "time (s): mean", "time / global"], out))


def stage_table(stages: list[StageTimes]) -> str:
    """Per set, clean or noisy, and method: the mean seconds of each stage over the runs that returned a model
    (ours: `AlignStats.timings_s`; pycolmap: `run_colmap`'s), in the order the stages ran."""
    groups: dict[tuple[str, str], list[dict[str, float]]] = {}
    for label, method, t in stages:
        key = label.split(" (noise seed")[0].split(", EXIF")[0]
        groups.setdefault((key, method), []).append(t)
    rows = []
    for (key, method), ts in groups.items():
        names = list(dict.fromkeys(k for t in ts for k in t))
        means = {k: float(np.mean([t.get(k, 0.0) for t in ts])) for k in names}
        rows.append([key, method, len(ts), sum(means.values()), ", ".join(f"{k} {v:.2f}" for k, v in means.items())])
    return ("\nWhere the time goes: per set and method, the mean seconds of each stage over the runs with a model "
            "(`runs`). Ours (`AlignStats.timings_s`): `pairwise` is SIFT, matching, the relative poses and the "
            "dense pairwise pointmaps on a thread per core; `global_align` the start's initial values and the "
            "DUSt3R alignment; the later stages run on one core. pycolmap (`run_colmap`): `features` and "
            "`matching` on every core, `mapping` the mapper.\n\n"
            + md_table(["set", "method", "runs", "stages (s)", "per stage (s)"], rows))


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    logging.basicConfig(level=logging.ERROR)
    os.environ.setdefault("DGS_NO_PROGRESS", "1")

    opt = cli_option

    which = opt("sets", "temple,dtu_spread,dtu_cluster,data").split(",")
    noise = opt("noise", "clean,noisy").split(",")
    methods = [m for m in METHODS if m in opt("methods", ",".join(DEFAULT_METHODS)).split(",")]
    out_name = opt("out", "real")
    n_seeds = int(opt("noise-seeds", "6"))
    exif = "--exif" in sys.argv
    sets: list[RealSet] = []
    missing = []
    found = [(temple_set, "temple", TEMPLE), (lambda: dtu_set("spread"), "dtu_spread", DTU),
             (lambda: dtu_set("cluster"), "dtu_cluster", DTU)]
    for make, key, where in found:
        if key in which:
            s = make()
            if s is None:
                missing.append(str(where))
            else:
                sets.append(s)
    if "data" in which:
        for d in filter(None, opt("data", "").split(",")):
            s = folder_set(Path(d))
            if s:
                sets.append(s)
    for m in sorted(set(missing)):
        print(f"note: {m} is missing; its sets are skipped", file=sys.stderr)
    if not sets:
        print("no real image set is available (../shared/data missing and no --data): nothing to benchmark")
        return 0
    load0 = os.getloadavg()
    rows, pair_counts, stages = [], [], []
    k = 0
    with tempfile.TemporaryDirectory(prefix="bench-real-") as tmp:
        work = Path(tmp)
        for si, s in enumerate(sets):
            wh = read_image(s.files[0]).shape[1::-1]
            cams_txt = write_cameras_txt(s.K, wh, work / f"cams_{si}")
            f_ref = float(s.K[0, 0])
            variants = [(v, seed) for v in noise for seed in (range(n_seeds) if v == "noisy" else [0])]
            f35 = exif_focal_35mm_of(s.K, wh) if exif else None
            for variant, seed in variants:
                if variant == "noisy" and not s.add_noise and "clean" in noise:
                    continue
                folder = prepare(s, work, variant == "noisy", seed, f35)
                label = f"{s.name}, {variant}" if s.add_noise else s.name
                if variant == "noisy" and seed:
                    label += f" (noise seed {seed})"
                if f35 is not None:
                    label += f", EXIF {f35} mm"
                order = methods[k % len(methods):] + methods[:k % len(methods)]
                k += 1
                for m in order:
                    if m == "ours":
                        r = run_ours(label, "ours", folder, s.gt, f_ref, None, OURS, stages)
                    elif m == "ours_noexif":
                        r = run_ours(label, "ours, EXIF off", folder, s.gt, f_ref, None,
                                     replace(OURS, exif_focal=False), stages)
                    elif m == "ours_intr":
                        r = run_ours(label, "ours --intrinsics", folder, s.gt, f_ref, cams_txt, OURS, stages)
                    elif m in ("ours_chain", "ours_averaged"):
                        start = m.split("_")[1]
                        r = run_ours(label, f"ours --initial-poses {start}", folder, s.gt, f_ref, None,
                                     replace(OURS, initial_poses=start), stages)
                    elif m == "ours_partial":
                        r = run_ours(label, "ours --allow-partial", folder, s.gt, f_ref, None,
                                     replace(OURS, allow_partial=True), stages)
                    elif m == "ours_intr_partial":
                        r = run_ours(label, "ours --intrinsics --allow-partial", folder, s.gt, f_ref, cams_txt,
                                     replace(OURS, allow_partial=True), stages)
                    elif m == "global_intr":
                        known = (float(s.K[0, 0]), float(s.K[1, 1]), float(s.K[0, 2]), float(s.K[1, 2]))
                        r = run_pycolmap(label, "global", folder, s.gt, f_ref, stages, known_pinhole=known)
                    else:
                        r = run_pycolmap(label, m, folder, s.gt, f_ref, stages)
                    rows.append(r)
                    print(r, file=sys.stderr, flush=True)
                if "--no-colmap-pairs" not in sys.argv:
                    n = colmap_verified_pairs(folder, sorted(s.gt))
                    pair_counts.append((label, n))
                    print(f"{label}: COLMAP exhaustive matching verifies {n} pairs", file=sys.stderr, flush=True)
    load1 = os.getloadavg()
    cpu = subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True, text=True).stdout.strip()
    cmd = "python benchmarks/bench_real.py " + " ".join(sys.argv[1:])
    body = (f"Command: `{cmd.strip()}`. Machine: {cpu.split(':', 1)[-1].strip()}, {os.cpu_count()} cores; "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Load average (1/5/15 min) at start "
            f"{load0[0]:.2f}/{load0[1]:.2f}/{load0[2]:.2f}, at end {load1[0]:.2f}/{load1[1]:.2f}/{load1[2]:.2f}.\n\n"
            "12 training views per set; `noisy` adds Gaussian noise sigma 25/255 (seed 0; with --noise-seeds, "
            "seeds 0..N-1) to the clean 8-bit images. Rotation errors are over all pairs of registered views "
            "(relative rotations, in deg); "
            "ATE / scale is the RMSE of the camera centres after Sim(3) alignment over the RMS distance of the "
            "reference centres to their centroid. `ours` is `mvgeo align` without the dense stereo (poses and "
            "sparse points, as the mappers return); `pairs` is verified pairs / all pairs; `tracks` the bundle "
            "adjustment's tracks (ours) or the model's points (pycolmap). See the script's docstring.\n\n")
    if exif:
        body += ("`--exif`: every image file carries the EXIF FocalLengthIn35mmFilm a camera would write for the "
                 "set's calibration (whole millimetres, named in the set column; the same pixels); `ours` starts "
                 "its pairs there (`AlignConfig.exif_focal`) and pycolmap's image reader takes it as its prior "
                 "focal.\n\n")
    body += md_table(["set", "method", "registered", "rot med (deg)", "rot max (deg)", "transl dir (deg)",
                      "ATE / scale", "focal err %", "time (s)", "pairs", "tracks", "note"], rows)
    if n_seeds > 1:
        body += noise_seed_summary(rows, n_seeds)
    if stages:
        body += stage_table(stages)
    if pair_counts:
        body += ("\nVerified pairs of pycolmap's exhaustive matching (two-view geometries with >= 15 inliers, of "
                 "66): " + ", ".join(f"{a}: {b}" for a, b in pair_counts) + "\n")
    if missing:
        body += "\nMissing (skipped): " + ", ".join(sorted(set(missing))) + "\n"
    print(write_fragment(out_name, "Real photographs: mvgeo align vs pycolmap incremental and global", body,
                         None if out_name == "real" else "the command below (`benchmarks/bench_real.py`)"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
