"""What accuracy costs in time on real photographs: `mvgeo align` options swept one at a time around the defaults.

Usage: `python benchmarks/bench_real_sweep.py [--sets=temple,dtu_spread,dtu_cluster]
[--noise=clean,noisy] [--factors=features,contrast,size,iters,ba,init,frontend] [--values=A;B] [--colmap-pairs]
[--fresh] [--report] [--out=NAME]` (writes docs/bench/NAME.md, default `real_sweep`, its rows in
docs/bench/NAME.json and a plot docs/bench/NAME.png). The sweep runs in pieces: each run replaces its own rows
(same set, noise, factor and value) in NAME.json and rewrites the table from all rows; `--fresh` starts from
none; `--report` only rewrites NAME.md and the plot from NAME.json. Text under a `### Reading` heading of an
existing NAME.md is kept. Without `--factors` every factor but `frontend` runs.

Sets and noise: those of `benchmarks/bench_real.py` (its set preparation is imported: 12 views, clean and with
Gaussian noise sigma 25/255 added, seed 0). Every configuration is `mvgeo align` without the dense stereo
(poses and sparse points, bench_real's `ours`), without known intrinsics, in this one process; within one set
and noise the configurations are run in turn, the order rotating from one set and noise to the next.

Factors (each changes one option of the defaults, `AlignConfig()`; `*` marks the default's value):
- `features`: `pairwise.sift_features` 2000 / 4000* / 8000 (the cap on keypoints per image);
- `contrast`: `pairwise.sift_contrast_threshold` 0.04* / 0.02 / 0.01 (detector sensitivity: what limits the
  keypoints on these images);
- `size`: `max_size_px` 384 / 512 / 640* / 800, the values below the image's long side (images are never
  upsampled; DTU is 384x384, so only the default);
- `iters`: `align.iters` 0 / 50 / 100* / 300 (DUSt3R global-alignment Adam iterations);
- `ba`: `bundle_adjust` on* / off / off with the verdict's pair checks off (`max_unexplained_fraction` 1,
  `reject_unsupported_views` False: the global alignment's poses, which the verdict refuses on these sets);
- `init`: `initial_poses` auto* / chain / averaged;
- `frontend`: pair front-end settings that may densify the match graph: contrast 0.02 and 0.01, no pre-blur,
  no pre-blur with contrast 0.01, ratio 0.85 and 0.9, `min_matches` 15, the two-view inlier minimum 10,
  RANSAC threshold 2 px, contrast 0.02 with ratio 0.85.

`--values=A;B` runs only the values labelled A or B (without the `*`), e.g. `--values="ratio 0.85;0.02"`.

Columns: keypoints per image (mean over the images of the detection run the pair stage kept: the sensitive
fallback's when it ran, `note`); registered / total; rotation error median and max over all pairs of
registered views (deg, `mvgeo.metrics.compare_poses`); ATE RMSE after Sim(3) / scene scale; focal error %;
verified pairs (`AlignStats.n_pairs_verified`: the pair stage's relative poses, of 66); wrong pairs, two tests
of each verified pair of the first pair stage: `rot`, its rotation re-estimated from its inlier matches with the
reference calibration (USAC_MAGSAC essential matrix, seed 0) is more than 5 deg off the reference relative
rotation (the pair stage's own rotation is at its first focal estimate, on these sets the prior, half the true
focal, so it is several degrees off on most pairs and not tabulated; NAME.json has it as `wrong_own`);
`matches`, fewer than half of its inlier matches lie within 2 px (Sampson distance) of the reference epipolar
geometry; seconds: wall-clock in total, CPU time of this process in total (all its threads: less sensitive to
the other processes on a shared machine than the wall-clock), and wall-clock of the pairwise stage
(`AlignStats.timings_s["pairwise"]`: features, matching, relative poses, dense pointmaps).

`--colmap-pairs` also counts pycolmap's verified pairs after its feature extraction and exhaustive matching
(two-view geometries with >= 15 inliers, untimed) and how many of them are wrong by the same two tests.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import ROOT, cli_option, md_table, write_fragment
from bench_real import OURS, RealSet, dtu_set, prepare, scene_scale, temple_set

from mvgeo.align.api import align_images
from mvgeo.align.classical_pairs import ClassicalPointmapModel
from mvgeo.align.config import AlignConfig
from mvgeo.align.features import MatchSet
from mvgeo.align.pairs import PairSet
from mvgeo.common.deps import cv2
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import compare_poses
from mvgeo.transforms import skew

WRONG_PAIR_DEG = 5.0
#: a match agrees with the reference two-view geometry within this Sampson distance (px at the matching size).
EPIPOLAR_PX = 2.0
FACTORS = ("features", "contrast", "size", "iters", "ba", "init", "frontend")
SETS = {"temple": temple_set, "dtu_spread": lambda: dtu_set("spread"), "dtu_cluster": lambda: dtu_set("cluster")}
HEADER = ["set", "noise", "factor", "value", "kp/img", "registered", "rot med (deg)", "rot max (deg)",
          "ATE / scale", "focal err %", "verified pairs", "wrong: rot / matches", "time (s)", "CPU (s)", "pairwise (s)",
          "note"]


def _pw(cfg: AlignConfig, **kw) -> AlignConfig:
    return replace(cfg, pairwise=replace(cfg.pairwise, **kw))


def variants(factor: str, long_side_px: int, base: AlignConfig = OURS) -> list[tuple[str, AlignConfig]]:
    """(value label, configuration) of one factor; the default's label ends in `*`."""
    p = base.pairwise
    if factor == "features":
        return [(f"{n}{'*' if n == p.sift_features else ''}", _pw(base, sift_features=n)) for n in (2000, 4000, 8000)]
    if factor == "contrast":
        return [(f"{c:g}{'*' if c == p.sift_contrast_threshold else ''}", _pw(base, sift_contrast_threshold=c))
                for c in (0.04, 0.02, 0.01)]
    if factor == "size":
        out = [(f"{s}", replace(base, max_size_px=s)) for s in (384, 512, 640, 800)
               if s < long_side_px and s != base.max_size_px]
        return out + [(f"{min(base.max_size_px, long_side_px)}*", base)]
    if factor == "iters":
        return [(f"{n}{'*' if n == base.align.iters else ''}", replace(base, align=replace(base.align, iters=n)))
                for n in (0, 50, 100, 300)]
    if factor == "ba":
        off = replace(base, bundle_adjust=False)
        return [("on*", base), ("off", off),
                ("off, no verdict", replace(off, max_unexplained_fraction=1.0, reject_unsupported_views=False))]
    if factor == "init":
        return [(f"{s}{'*' if s == base.initial_poses else ''}", replace(base, initial_poses=s))
                for s in ("auto", "chain", "averaged")]
    if factor == "frontend":
        tv = p.two_view
        return [("defaults*", base),
                ("contrast 0.02", _pw(base, sift_contrast_threshold=0.02)),
                ("contrast 0.01", _pw(base, sift_contrast_threshold=0.01)),
                ("no blur", _pw(base, sift_blur_sigma_px=0.0)),
                ("no blur, contrast 0.01", _pw(base, sift_blur_sigma_px=0.0, sift_contrast_threshold=0.01)),
                ("ratio 0.85", _pw(base, ratio=0.85)),
                ("ratio 0.9", _pw(base, ratio=0.9)),
                ("min_matches 15", _pw(base, min_matches=15)),
                ("min_inliers 10", _pw(base, two_view=replace(tv, min_inliers=10))),
                ("RANSAC 2 px", _pw(base, two_view=replace(tv, ransac=replace(tv.ransac, threshold_px=2.0)))),
                ("contrast 0.02, ratio 0.85", _pw(base, sift_contrast_threshold=0.02, ratio=0.85))]
    raise ValueError(f"unknown factor {factor!r}")


class RecordingModel(ClassicalPointmapModel):
    """The default pair model, keeping the first `PairSet` and the `MatchSet` it was computed from."""

    first_pairs: PairSet | None = None
    last_matches: MatchSet | None = None

    def match(self, images, pairs) -> MatchSet:
        ms = super().match(images, pairs)
        self.last_matches = ms
        return ms

    def predict_pairs(self, images, pairs) -> PairSet:
        ps = super().predict_pairs(images, pairs)
        if self.first_pairs is None:
            self.first_pairs = ps
        return ps


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix (3, 3), deg."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def rotation_from_matches(uv_i: np.ndarray, uv_j: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """cam_j_from_cam_i rotation (3, 3) from matched pixels (M, 2) under the calibration K (3, 3), or None."""
    if len(uv_i) < 5:
        return None
    a, b = np.ascontiguousarray(uv_i, np.float64), np.ascontiguousarray(uv_j, np.float64)
    E, mask = cv2.findEssentialMat(a, b, K, method=cv2.USAC_MAGSAC, prob=0.9999, threshold=1.0)
    if E is None or E.shape != (3, 3):
        return None
    _, R, _, _ = cv2.recoverPose(E, a, b, K, mask=mask)
    return R


def sampson_px(F: np.ndarray, uv_i: np.ndarray, uv_j: np.ndarray) -> np.ndarray:
    """Sampson distances (M,) of matches (M, 2), (M, 2) under the fundamental matrix F (x_j^T F x_i = 0), px."""
    xi = np.hstack([uv_i, np.ones((len(uv_i), 1))])
    xj = np.hstack([uv_j, np.ones((len(uv_j), 1))])
    Fx, Ftx = xi @ F.T, xj @ F
    num = np.sum(xj * Fx, axis=1) ** 2
    return np.sqrt(num / np.maximum(Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2, 1e-30))


def pair_errors(pairs: Sequence[tuple[str, str, np.ndarray | None, np.ndarray]], gt: dict[str, np.ndarray],
                K: np.ndarray) -> dict[str, list[float]]:
    """Per verified pair, against the reference poses `gt` (name: cam_from_world (3, 4)) and calibration K (3, 3):

    - "own": rotation error of the pair's own estimate (deg; NaN: none);
    - "true_k": rotation error of its rotation re-estimated from its inlier matches with K (deg; 180: none);
    - "epipolar": fraction of its inlier matches within `EPIPOLAR_PX` (Sampson distance) of the reference
      epipolar geometry.

    pairs: (name i, name j, own cam_j_from_cam_i rotation (3, 3) or None, inlier matches (M, 4) in pixels of
    the images K refers to).
    """
    out: dict[str, list[float]] = {"own": [], "true_k": [], "epipolar": []}
    Kinv = np.linalg.inv(K)
    for ni, nj, R_own, m in pairs:
        R_gt = gt[nj][:, :3] @ gt[ni][:, :3].T
        t_gt = gt[nj][:, 3] - R_gt @ gt[ni][:, 3]
        out["own"].append(float("nan") if R_own is None else rotation_angle_deg(R_own @ R_gt.T))
        cv2.setRNGSeed(0)
        R = rotation_from_matches(m[:, :2], m[:, 2:], K)
        out["true_k"].append(180.0 if R is None else rotation_angle_deg(R @ R_gt.T))
        F = Kinv.T @ skew(t_gt) @ R_gt @ Kinv
        out["epipolar"].append(float(np.mean(sampson_px(F, m[:, :2], m[:, 2:]) < EPIPOLAR_PX)))
    return out


def count_wrong(err: dict[str, list[float]]) -> dict[str, int]:
    """Wrong pairs by each test of `pair_errors`: rotation more than 5 deg off, or most matches off the truth."""
    return {"wrong_own": int(np.sum(np.asarray(err["own"]) > WRONG_PAIR_DEG)),
            "wrong_true_k": int(np.sum(np.asarray(err["true_k"]) > WRONG_PAIR_DEG)),
            "wrong_matches": int(np.sum(np.asarray(err["epipolar"]) < 0.5))}


def run_config(s: RealSet, folder: Path, cfg: AlignConfig) -> dict:
    """One `align_images` run (timed) and its scores (untimed) as a row dict."""
    paths = [p for p in list_images(folder) if p.name in s.gt]
    # The model `align_images` would make (no known intrinsics), recording its pair stage.
    model = RecordingModel(cfg.pairwise, K_align=None, seed=cfg.seed)
    row: dict = {}
    t, cpu = time.perf_counter(), time.process_time()
    try:
        res = align_images(paths, cfg, model=model)
        err = ""
    except Exception as exc:  # report, keep benchmarking
        res, err = None, f"{type(exc).__name__}: {exc}".replace("|", "/").replace("\n", " ")[:160]
    row["seconds"], row["cpu_s"] = time.perf_counter() - t, time.process_time() - cpu
    names = [p.name for p in paths]
    if model.last_matches is not None:
        row["kp_per_image"] = float(np.mean([len(f.uv_px) for f in model.last_matches.features]))
        row["sensitive"] = bool(model.last_matches.sensitive)
    if model.first_pairs is not None:
        wa = model.last_matches.image_hw[1] if model.last_matches is not None else None
        w0 = read_image(paths[0]).shape[1]
        K = s.K.copy()
        if wa is not None:
            K[:2] *= wa / w0
        geo = [(names[g.i], names[g.j], None if g.cam_j_from_cam_i is None else g.cam_j_from_cam_i[:, :3],
                g.matches_px) for g in model.first_pairs.geometries]
        row["verified"] = len(geo)
        row.update(count_wrong(pair_errors(geo, s.gt, K)))
    if res is None:
        row.update(registered=0, error=err)
        return row
    st = res.stats
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), s.gt)
    rot = m.rotation_deg
    f = float(np.median([c.fx for c in res.sparse_model.cameras.values()]))
    row.update(registered=m.n_registered, rot_med=m.median_rotation_deg,
               rot_max=float(rot.max()) if rot.size else float("nan"),
               ate=m.ate.rmse / scene_scale(s.gt) if m.ate is not None else float("nan"),
               focal_err=abs(f / float(s.K[0, 0]) - 1.0) * 100.0, n_pairs=st.n_pairs,
               pairwise_s=float(st.timings_s.get("pairwise", float("nan"))),
               timings_s={k: round(float(v), 3) for k, v in st.timings_s.items()},
               note="; ".join(x for x in [f"{st.initial_poses} start, {len(st.candidates)} candidate(s)",
                                          f"{len(st.pairs_rejected_by_loops)} rejected by loops"
                                          if st.pairs_rejected_by_loops else "",
                                          f"BA {st.bundle_adjustment.n_points} tracks"
                                          if st.bundle_adjustment is not None else "no BA"] if x))
    return row


def colmap_pairs(folder: Path, names: Sequence[str], s: RealSet, min_inliers: int = 15) -> dict:
    """pycolmap's verified pairs after extraction and exhaustive matching, and how many are wrong under the
    reference calibration (same test as ours)."""
    from mvgeo.common.deps import pycolmap

    with tempfile.TemporaryDirectory(prefix="bench-sweep-db-") as tmp:
        db_path = Path(tmp) / "database.db"
        ext = pycolmap.FeatureExtractionOptions()
        ext.use_gpu = False
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        pycolmap.extract_features(db_path, folder, image_names=list(names), camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(db_path, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(db_path)
        try:
            name_of = {im.image_id: im.name for im in db.read_all_images()}
            kp = {i: db.read_keypoints(i)[:, :2].astype(np.float64) for i in name_of}
            pair_ids, geoms = db.read_two_view_geometries()
            bad = {pycolmap.TwoViewGeometryConfiguration.UNDEFINED, pycolmap.TwoViewGeometryConfiguration.DEGENERATE}
            geo = []
            for pid, g in zip(pair_ids, geoms, strict=True):
                if g.config in bad or len(g.inlier_matches) < min_inliers:
                    continue
                a, b = pycolmap.pair_id_to_image_pair(pid)
                m = np.asarray(g.inlier_matches)
                geo.append((name_of[a], name_of[b], None, np.concatenate([kp[a][m[:, 0]], kp[b][m[:, 1]]], axis=1)))
        finally:
            db.close()
    wrong = count_wrong(pair_errors(geo, s.gt, s.K))
    return {"verified": len(geo), "wrong_true_k": wrong["wrong_true_k"], "wrong_matches": wrong["wrong_matches"]}


def _fmt_row(r: dict) -> list:
    wrong = f"{r['wrong_true_k']} / {r['wrong_matches']}" if "verified" in r else ""
    note = r.get("note", "") if not r.get("error") else f"failed: {r['error']}"
    if r.get("sensitive"):
        note = "sensitive SIFT; " + note
    return [r["set"], r["noise"], r["factor"], r["value"], round(r["kp_per_image"]) if "kp_per_image" in r else "",
            f"{r['registered']}/12", r.get("rot_med", ""), r.get("rot_max", ""), r.get("ate", ""),
            r.get("focal_err", ""), f"{r['verified']}/66" if "verified" in r else "", wrong, r["seconds"],
            r.get("cpu_s", ""), r.get("pairwise_s", ""), note]


def plot(rows: list[dict], path: Path) -> Path | None:
    """Rotation error median against CPU seconds, one marker shape per set and noise, one colour per factor (PNG)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    ok = [r for r in rows if r.get("registered", 0) == 12 and np.isfinite(r.get("rot_med", np.nan))]
    if not ok:
        return None
    markers = dict(zip(sorted({(r["set"], r["noise"]) for r in ok}), "osD^vP*X", strict=False))
    colours = dict(zip(FACTORS, plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False))
    fig, ax = plt.subplots(figsize=(7.5, 5))
    seen = set()  # one marker per run: a run shared by several factors is drawn under the first
    for r in sorted(ok, key=lambda r: FACTORS.index(r["factor"])):
        run = (r["set"], r["noise"], r["seconds"])
        if run in seen:
            continue
        seen.add(run)
        default = r["value"].endswith("*")
        x = r.get("cpu_s", r["seconds"])
        ax.scatter(x, r["rot_med"], marker=markers[(r["set"], r["noise"])],
                   color="black" if default else colours[r["factor"]], s=36, alpha=0.8)
        if not default:
            ax.annotate(r["value"], (x, r["rot_med"]), fontsize=6, xytext=(3, 2),
                        textcoords="offset points")
    for (sname, noise), mk in markers.items():
        ax.scatter([], [], marker=mk, color="gray", label=f"{sname}, {noise}")
    ax.scatter([], [], marker="s", color="black", label="defaults")
    for fac, col in colours.items():
        if any(r["factor"] == fac for r in ok):
            ax.scatter([], [], marker="s", color=col, label=fac)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("CPU seconds of the mvgeo align call (poses only; shared, loaded machine)")
    ax.set_ylabel("rotation error median (deg)")
    ax.set_title("Accuracy against time, one factor changed at a time (12/12 registered only)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    logging.basicConfig(level=logging.ERROR)
    os.environ.setdefault("DGS_NO_PROGRESS", "1")

    opt = cli_option

    which = opt("sets", ",".join(SETS)).split(",")
    noise = opt("noise", "clean,noisy").split(",")
    factors = opt("factors", ",".join(f for f in FACTORS if f != "frontend")).split(",")
    unknown = [x for x in which if x not in SETS] + [x for x in factors if x not in FACTORS] + \
        [x for x in noise if x not in ("clean", "noisy")]
    if unknown:
        print(f"error: unknown --sets/--factors/--noise value(s): {', '.join(unknown)}", file=sys.stderr)
        return 2
    out_name = opt("out", "real_sweep")
    only_values = [v for v in opt("values", "").split(";") if v]
    store = ROOT / "docs" / "bench" / f"{out_name}.json"
    data = {"runs": [], "rows": [], "colmap": []}
    if store.is_file() and "--fresh" not in sys.argv:
        data = json.loads(store.read_text())
    if "--report" in sys.argv:
        print(write_report(data, out_name))
        return 0
    sets = []
    for key in which:
        s = SETS[key]()
        if s is None:
            print(f"note: set {key} is missing (../shared/data); skipped", file=sys.stderr)
        else:
            sets.append(s)
    if not sets:
        print("no real image set is available (../shared/data missing): nothing to benchmark")
        return 0
    load0 = os.getloadavg()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    newest = max(f.stat().st_mtime for f in (ROOT / "mvgeo" / "align").glob("*.py"))
    code = f"HEAD {head.strip()} + working tree (mvgeo/align changed {time.strftime('%H:%M', time.gmtime(newest))})"
    t_start = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    new_rows, new_colmap = [], []
    k = 0
    with tempfile.TemporaryDirectory(prefix="bench-real-sweep-") as tmp:
        for s in sets:
            long_side = max(read_image(s.files[0]).shape[:2])
            for variant in noise:
                folder = prepare(s, Path(tmp), variant == "noisy")
                runs: dict[str, list] = {}  # one run per distinct configuration, shared by the factors
                cfgs: dict[str, AlignConfig] = {}
                for fac in factors:
                    for value, cfg in variants(fac, long_side):
                        if only_values and value.rstrip("*") not in only_values:
                            continue
                        key = repr(cfg)
                        cfgs[key] = cfg
                        runs.setdefault(key, []).append((fac, value))
                keys = list(cfgs)
                order = keys[k % len(keys):] + keys[:k % len(keys)]
                k += 1
                for key in order:
                    r = run_config(s, folder, cfgs[key])
                    for fac, value in runs[key]:
                        row = {"set": s.name, "noise": variant, "factor": fac, "value": value, **r}
                        new_rows.append(row)
                        print(_fmt_row(row), file=sys.stderr, flush=True)
                if "--colmap-pairs" in sys.argv:
                    c = {"set": s.name, "noise": variant, **colmap_pairs(folder, sorted(s.gt), s)}
                    new_colmap.append(c)
                    print(c, file=sys.stderr, flush=True)
    load1 = os.getloadavg()
    cpu = subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True, text=True).stdout.strip()
    data["runs"].append({"command": "python benchmarks/bench_real_sweep.py " + " ".join(sys.argv[1:]),
                         "date": t_start, "machine": f"{cpu.split(':', 1)[-1].strip()}, {os.cpu_count()} cores",
                         "code": code, "load_start": [round(x, 2) for x in load0],
                         "load_end": [round(x, 2) for x in load1]})
    keyf = ("set", "noise", "factor", "value")
    done = {tuple(r[x] for x in keyf) for r in new_rows}
    data["rows"] = [r for r in data["rows"] if tuple(r[x] for x in keyf) not in done] + new_rows
    done_c = {(c["set"], c["noise"]) for c in new_colmap}
    data["colmap"] = [c for c in data["colmap"] if (c["set"], c["noise"]) not in done_c] + new_colmap
    store.write_text(json.dumps(data, indent=1, default=float))
    print(write_report(data, out_name))
    return 0


def write_report(data: dict, out_name: str) -> Path:
    """The markdown table (rows grouped by set, noise and factor) and the plot, from all stored rows."""
    sort_sets = {n: i for i, n in enumerate(["temple_sparse_ring", "dtu_scan24 (spread)", "dtu_scan24 (cluster)"])}
    rows = sorted(data["rows"], key=lambda r: (sort_sets.get(r["set"], 9), r["noise"] != "clean",
                                               FACTORS.index(r["factor"])))
    body = "Runs (each replaced its own rows; seconds compare only within one run, under its load):\n\n"
    for run in data["runs"]:
        body += (f"- `{run['command'].strip()}`: {run['date']}, {run['machine']}, {run.get('code', '')}, "
                 "load average (1/5/15 min) "
                 f"at start {'/'.join(map(str, run['load_start']))}, at end {'/'.join(map(str, run['load_end']))}\n")
    body += ("\n12 views per set, `noisy` = Gaussian sigma 25/255 added (seed 0). `mvgeo align` without the dense "
             "stereo and without known intrinsics; one option changed at a time, `*` = the default's value (one run "
             "of the defaults per set and noise, repeated under each factor). `wrong: rot / matches`: verified pairs "
             f"whose rotation re-estimated from their inlier matches with the reference calibration is more than "
             f"{WRONG_PAIR_DEG:g} deg off the reference / of whose inlier matches fewer than half lie within "
             f"{EPIPOLAR_PX:g} px (Sampson) of the reference epipolar geometry. See the script's docstring.\n\n")
    body += md_table(HEADER, [_fmt_row(r) for r in rows])
    if data["colmap"]:
        body += ("\npycolmap's exhaustive matching on the same images (two-view geometries with >= 15 inliers, of 66; "
                 "wrong by the same two tests): " +
                 ", ".join(f"{c['set']}, {c['noise']}: {c['verified']} verified, wrong {c['wrong_true_k']} / "
                           f"{c['wrong_matches']}"
                           for c in data["colmap"]) + "\n")
    png = plot(rows, ROOT / "docs" / "bench" / f"{out_name}.png")
    if png is not None:
        body += f"\n![rotation error median against CPU seconds]({png.name})\n"
    md = ROOT / "docs" / "bench" / f"{out_name}.md"
    reading = ""
    if md.is_file():
        text = md.read_text()
        if "\n### Reading" in text:
            reading = text[text.index("\n### Reading"):]
    path = write_fragment(out_name, "Real photographs: what accuracy costs in time (mvgeo align options swept)",
                          body + reading)
    return path


if __name__ == "__main__":
    raise SystemExit(main())
