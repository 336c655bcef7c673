"""mvgeo align vs pycolmap incremental SfM: pose accuracy and time.

Usage: `python benchmarks/bench_align.py [--scenes=llff_like,object_ring,temple,dtu,subsets] [--sweep] [--repeat=N]
[--out=NAME]` (writes docs/bench/NAME.md, default `align`; only the table and its header: the reading text is
added by hand).

Scenes: data_synth `llff_like` and `object_ring` rendered with 12 views
(noisy images, ground-truth poses); 3- and 6-view subsets of llff_like
(evenly spaced views); ../shared/data/temple_sparse_ring (12 of its 16 real
views, calibrated poses) and ../shared/data/dtu_scan24 (the 12 training views
of `python -m eval.datasets dtu --layout cluster`: about 11 deg apart, Gaussian
noise sigma 25/255 added with seed 0, 384x384, narrow field of view) when
present. `--sweep` adds variants of ours on
llff_like that show what accuracy costs: global-alignment iterations, its
pixel stride, --max-size, and the bundle adjustment on/off. Both methods run
in this one process, one after the other, so their time ratio is comparable.
`--repeat=N` times the llff_like poses-only comparison (ours with `--no-dense-stereo`, then pycolmap) N more
times, alternating, and lists each run's ratio: one run's ratio moves with the machine's load.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import ROOT, md_table, write_fragment

from mvgeo.align.api import AlignConfig, align_images
from mvgeo.align.colmap_sfm import ColmapConfig, run_colmap
from mvgeo.align.dense_stereo import DenseStereoConfig
from mvgeo.common.imageio import list_images
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model

TEMPLE = ROOT.parent / "shared" / "data" / "temple_sparse_ring"
DTU = ROOT.parent / "shared" / "data" / "dtu_scan24"
DEFAULT = AlignConfig()


def temple_ground_truth(folder: Path, names: list[str]) -> dict[str, np.ndarray]:
    lines = (folder / "templeSR_par.txt").read_text().split("\n")[1:]
    out = {}
    for line in lines:
        parts = line.split()
        if len(parts) == 22 and parts[0] in names:
            v = np.array([float(x) for x in parts[1:]])
            out[parts[0]] = np.concatenate([v[9:18].reshape(3, 3), v[18:21].reshape(3, 1)], axis=1)
    return out


def _subset_dir(work: Path, name: str, src: Path, names: list[str]) -> Path:
    sub = work / name
    sub.mkdir()
    for n in names:
        (sub / n).symlink_to(src / n)
    return sub


def scenes(work: Path, which: list[str]):
    from data_synth import render_scene

    for name in ("llff_like", "object_ring"):
        if name in which or (name == "llff_like" and "subsets" in which):
            d = render_scene(name, work / name, views=12)
            ref = read_sparse_model(d / "sparse" / "0")
            gt, f = ref.cam_from_world_by_name(), ref.cameras[ref.images[0].camera_id].fx
            if name in which:
                yield name, d / "images", gt, f
            if name == "llff_like" and "subsets" in which:
                all_names = sorted(gt)
                for k in (3, 6):
                    pick = [all_names[i] for i in np.linspace(0, 11, k).round().astype(int)]
                    sub = _subset_dir(work, f"llff{k}", d / "images", pick)
                    yield f"llff_like ({k} views)", sub, {n: gt[n] for n in pick}, f
    if "temple" in which:
        if not TEMPLE.is_dir():
            print(f"note: {TEMPLE} missing, temple scene skipped", file=sys.stderr)
            return
        imgs = TEMPLE if list(TEMPLE.glob("*.png")) else TEMPLE / "images"
        names = [p.name for p in list_images(imgs)]
        names = [names[k] for k in np.linspace(0, len(names) - 1, 12).round().astype(int)]
        sub = _subset_dir(work, "temple12", imgs, names)
        lines = (TEMPLE / "templeSR_par.txt").read_text().split("\n")[1:]
        f = float([ln.split() for ln in lines if ln.split() and ln.split()[0] == names[0]][0][1])
        yield "temple_sparse_ring (12)", sub, temple_ground_truth(TEMPLE, names), f
    if "dtu" in which:
        if not DTU.is_dir():
            print(f"note: {DTU} missing, DTU scene skipped", file=sys.stderr)
            return
        from eval.datasets import dtu_dataset

        ds = dtu_dataset(DTU, work / "dtu", sigma_8bit=25.0, train_views=12, test_views=4, layout="cluster")
        train = json.loads((ds / "split.json").read_text())["train"]
        ref = read_sparse_model(ds / "sparse" / "0")
        gt = {n: g for n, g in ref.cam_from_world_by_name().items() if n in train}
        yield "dtu_scan24 + noise (12, cluster)", _subset_dir(work, "dtu12", ds / "images", train), gt, \
            ref.camera_of(train[0]).fx


def row(scene, method, est: dict, ref: dict, f_est, f_ref, seconds, extra=""):
    m = compare_poses(est, ref)
    return [scene, method, f"{m.n_registered}/{m.n_ref}", m.median_rotation_deg, m.median_translation_deg,
            m.ate.rmse if m.ate is not None else float("nan"), abs(f_est / f_ref - 1) * 100, seconds, extra]


def _ours(scene, label, cfg, paths, ref, f_ref):
    t = time.perf_counter()
    try:
        res = align_images(paths, cfg)
    except Exception as exc:  # report, keep benchmarking
        return [scene, label, f"failed: {type(exc).__name__}: {exc}"[:160], "", "", "", "", time.perf_counter() - t,
                ""]
    sec = time.perf_counter() - t
    f = float(np.median([c.fx for c in res.sparse_model.cameras.values()]))
    st = res.stats
    ba = st.bundle_adjustment
    extra = (f"reproj RMS {ba.reproj_rms_before_px:.3g} -> {ba.reproj_rms_after_px:.3g} px" if ba else "no BA")
    extra += f"; {st.initial_poses} start, {len(st.candidates)} candidate(s)"
    if st.unregistered:
        extra += f"; {len(st.unregistered)} unregistered"
    if st.pairs_rejected_by_loops:
        extra += "; loop check rejected " + ", ".join(f"{r.i[-8:-4]}-{r.j[-8:-4]}" for r in st.pairs_rejected_by_loops)
    return row(scene, label, res.sparse_model.cam_from_world_by_name(), ref, f, f_ref, sec, extra)


def _colmap(scene, images, paths, ref, f_ref):
    t = time.perf_counter()
    try:
        col = run_colmap(images, ColmapConfig(), image_names=[p.name for p in paths])
    except Exception as exc:
        return [scene, "pycolmap incremental", f"failed: {exc}"[:100], "", "", "", "", time.perf_counter() - t, ""]
    sec = time.perf_counter() - t
    f = float(np.median([c.fx for c in col.sparse_model.cameras.values()]))
    return row(scene, "pycolmap incremental", col.sparse_model.cam_from_world_by_name(), ref, f, f_ref, sec)


def sweep_variants() -> list[tuple[str, AlignConfig]]:
    a = DEFAULT.align
    return [
        ("ours, GA 0 it (MST init) + BA", replace(DEFAULT, candidate_align_iters=0)),
        ("ours, GA 300 it + BA", replace(DEFAULT, align=replace(a, iters=300))),
        ("ours, GA 300 it stride 1 + BA", replace(DEFAULT, align=replace(a, iters=300, pixel_stride=1))),
        (f"ours, GA {DEFAULT.align.iters} it, no BA", replace(DEFAULT, bundle_adjust=False)),
        ("ours, GA 300 it stride 1, no BA", replace(DEFAULT, bundle_adjust=False,
                                                   align=replace(a, iters=300, pixel_stride=1))),
        ("ours, --max-size 256", replace(DEFAULT, max_size_px=256)),
        ("ours, --max-size 384", replace(DEFAULT, max_size_px=384)),
    ]


#: Scenes where not every view can be connected or verified: also run ours with --allow-partial.
PARTIAL_SCENES = ("temple_sparse_ring (12)", "object_ring")


def main() -> None:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return
    logging.basicConfig(level=logging.WARNING)
    only = [a.split("=", 1)[1] for a in sys.argv if a.startswith("--scenes=")]
    which = only[0].split(",") if only else ["llff_like", "object_ring", "temple", "dtu", "subsets"]
    out_name = ([a.split("=", 1)[1] for a in sys.argv if a.startswith("--out=")] or ["align"])[0]
    sweep = "--sweep" in sys.argv
    repeat = int(([a.split("=", 1)[1] for a in sys.argv if a.startswith("--repeat=")] or ["0"])[0])
    repeats: list[tuple[float, float]] = []
    load0 = os.getloadavg()
    rows, ratios, ratios_sparse = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for scene, images, ref, f_ref in scenes(Path(tmp), which):
            paths = [p for p in list_images(images) if p.name in ref]
            ours = _ours(scene, "ours (defaults)", DEFAULT, paths, ref, f_ref)
            rows.append(ours)
            print(rows[-1], file=sys.stderr)
            col = _colmap(scene, images, paths, ref, f_ref)
            rows.append(col)
            print(rows[-1], file=sys.stderr)
            ratios.append((scene, ours[7] / col[7]))
            if scene not in PARTIAL_SCENES:
                # What pycolmap's mapper returns (poses + sparse points): ours without the final dense stereo.
                rows.append(_ours(scene, "ours (--no-dense-stereo)",
                                  replace(DEFAULT, dense_stereo=DenseStereoConfig(enabled=False)), paths, ref, f_ref))
                print(rows[-1], file=sys.stderr)
                ratios_sparse.append((scene, rows[-1][7] / col[7]))
            if scene in PARTIAL_SCENES:
                rows.append(_ours(scene, "ours (--allow-partial)", replace(DEFAULT, allow_partial=True), paths, ref,
                                  f_ref))
                print(rows[-1], file=sys.stderr)
            if repeat and scene == "llff_like":
                no_stereo = replace(DEFAULT, dense_stereo=DenseStereoConfig(enabled=False))
                for _ in range(repeat):
                    t_ours = _ours(scene, "", no_stereo, paths, ref, f_ref)[7]
                    t_col = _colmap(scene, images, paths, ref, f_ref)[7]
                    repeats.append((t_ours, t_col))
                    print(f"repeat: ours {t_ours:.2f} s, pycolmap {t_col:.2f} s", file=sys.stderr)
            if sweep and scene == "llff_like":
                for label, cfg in sweep_variants():
                    rows.append(_ours(scene, label, cfg, paths, ref, f_ref))
                    print(rows[-1], file=sys.stderr)
    load1 = os.getloadavg()
    body = ("Median relative rotation / translation-direction error over all image pairs (deg), ATE RMSE of "
            "camera centres after Sim(3) alignment (scene units), focal error (%), wall time (s), both methods "
            "in one process one after the other. `ours (defaults)` = classical pairwise pointmaps (SIFT + "
            f"OpenCV USAC + DIS flow, 128 px) + DUSt3R global alignment ({DEFAULT.align.iters} it, every "
            f"{DEFAULT.align.pixel_stride}th pixel) + Schur-complement LM bundle adjustment on the feature tracks, "
            "matching at 640 px, one BLAS/OpenCV thread per pool worker (2 workers); a COLMAP-like SIFT "
            "(lower contrast threshold, no blur) is tried when the match graph is disconnected; pairs whose "
            "relative rotation contradicts most of their loops of three pairs are rejected first, and a result "
            "whose relative rotations contradict a pair's matches fails. `ours (--allow-partial)` registers the "
            "largest group of images that can be connected and verified (rows: registered/all). "
            "`ours (defaults)` ends with the dense stereo on the final cameras (the output cloud, "
            f"{DEFAULT.dense_stereo.size_px} px, its wide holes filled); `ours (--no-dense-stereo)` skips it, "
            "so its cloud is the global alignment's: the product comparable to pycolmap's mapper "
            "(poses + sparse points). "
            f"Load average (1/5/15 min) at start {load0[0]:.2f}/{load0[1]:.2f}/{load0[2]:.2f}, at end "
            f"{load1[0]:.2f}/{load1[1]:.2f}/{load1[2]:.2f} on {os.cpu_count()} cores.\n\n")
    body += md_table(["scene", "method", "registered", "rot err (deg)", "transl err (deg)", "ATE", "focal err %",
                      "time (s)", "note"], rows)
    body += "\nTime ratio ours / pycolmap (same run): " + ", ".join(f"{s}: {r:.2f}" for s, r in ratios) + "\n"
    if ratios_sparse:
        body += ("\nTime ratio ours (--no-dense-stereo) / pycolmap (same run): "
                 + ", ".join(f"{s}: {r:.2f}" for s, r in ratios_sparse) + "\n")
    if repeats:
        body += (f"\nllff_like poses only, {len(repeats)} more runs alternating ours (--no-dense-stereo) and "
                 "pycolmap: " + ", ".join(f"{a:.2f} s / {b:.2f} s = {a / b:.3f}" for a, b in repeats) + "\n")
    if "temple" in which and not TEMPLE.is_dir():
        body += f"\n{TEMPLE} was missing: the real-data row is absent.\n"
    if "dtu" in which and not DTU.is_dir():
        body += f"\n{DTU} was missing: the DTU row is absent.\n"
    print(write_fragment(out_name, "mvgeo align vs pycolmap (pose accuracy, time)", body))


if __name__ == "__main__":
    main()
