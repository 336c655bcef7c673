"""Small real stage functions for testing the pipeline framework (not stand-ins for the product).

denoise = Gaussian blur; align = a known camera rig (the test scene's poses);
splat = the aligned points as a PLY point cloud; render = each camera's image
filled with the cloud's mean colour; select = the K sharpest views by Laplacian
variance; refine = a blur blended toward the previous render.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from eval.pipeline import PipelineStages, StageContext
from eval.pipeline.views import read_views, view_files, write_views
from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model


def make_scene(folder: Path, n: int = 5, size_wh: tuple[int, int] = (48, 40), seed: int = 0) -> Path:
    """Noisy textured PNGs `view_000.png`, ... in `folder`."""
    from mvgeo.common.imageio import write_image

    rng = np.random.default_rng(seed)
    w, h = size_wh
    base = cv2.GaussianBlur(rng.random((h + n * 2, w, 3)).astype(np.float32), (0, 0), 1.0)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        img = base[i * 2:i * 2 + h] + rng.normal(0, 0.05 * (1 + i % 3), (h, w, 3)).astype(np.float32)
        write_image(folder / f"view_{i:03d}.png", np.clip(img, 0, 1))
    return folder


def _write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(xyz)}", "property float x", "property float y",
             "property float z", "property uchar red", "property uchar green", "property uchar blue",
             "end_header"]
    lines += [f"{p[0]} {p[1]} {p[2]} {c[0]} {c[1]} {c[2]}" for p, c in zip(xyz, rgb, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def _read_ply_rgb(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()
    body = lines[lines.index("end_header") + 1:]
    return np.array([[int(v) for v in ln.split()[3:6]] for ln in body], np.float32) / 255.0


class TinyStages:
    """The stage functions plus a call counter (stage name -> calls)."""

    def __init__(self):
        self.calls: Counter[str] = Counter()
        self.fail_next: set[str] = set()
        #: When True, denoise writes the time into n2v_model.pt, as a checkpoint carrying a timestamp
        #: would: its outputs' bytes then differ from one run to the next.
        self.stamp_checkpoints = False
        #: When True, refine reports that its guard kept the previous network (as `eval.pipeline.stages.refine`
        #: records it), which ends the loop under `PipelineConfig.stop_when_unrefined`.
        self.refine_keeps_previous = False
        #: When True, denoise passes the photos through and writes no network, as the product's stage does for
        #: photos that read as clean (`DenoiseStageSettings.pass_clean_below_255`).
        self.passes_through = False

    def _enter(self, name: str) -> None:
        self.calls[name] += 1

    def _maybe_fail(self, name: str) -> None:
        """Called after a stage wrote part of its outputs: simulates Ctrl-C / a crash there."""
        if name in self.fail_next:
            self.fail_next.discard(name)
            raise KeyboardInterrupt(f"simulated interruption in {name}")

    def denoise(self, ctx: StageContext):
        self._enter("denoise")
        noisy = read_views(ctx.inputs["noisy"])
        if self.passes_through:
            write_views(ctx.work_dir / "denoised", noisy)
            return {"views": list(noisy), "passed_through": True}
        out = {k: cv2.GaussianBlur(v, (0, 0), 1.0) for k, v in noisy.items()}
        # Write one output, then (maybe) fail: a half-done stage must leave nothing behind.
        write_views(ctx.work_dir / "denoised", out)
        self._maybe_fail("denoise")
        stamp = {"saved_ns": time.time_ns()} if self.stamp_checkpoints else {}
        (ctx.work_dir / "n2v_model.pt").write_text(json.dumps({"sigma": 1.0, "seed": ctx.seed, **stamp}))
        return {"views": list(out)}

    def align(self, ctx: StageContext):
        self._enter("align")
        files = view_files(ctx.inputs["images"])
        img0 = read_image(next(iter(files.values())))
        h, w = img0.shape[:2]
        cam = Camera("PINHOLE", w, h, [50.0, 50.0, w / 2, h / 2])
        images = []
        for i, stem in enumerate(files):
            cfw = np.hstack([np.eye(3), [[-0.1 * i], [0.0], [0.0]]])
            images.append(PosedImage(f"{stem}.png", 1, cfw))
        rng = np.random.default_rng(ctx.seed)
        xyz = rng.normal(size=(20, 3)) + [0, 0, 4]
        rgb = (rng.random((20, 3)) * 255).astype(np.uint8)
        out = ctx.work_dir / "align"
        write_sparse_model(out / "sparse" / "0", SparseModel({1: cam}, images, xyz, rgb), binary=True)
        np.savez(out / "points.npz", xyz=xyz, rgb=rgb, conf=np.ones(len(xyz)))
        return {"registered": len(images)}

    def splat(self, ctx: StageContext):
        self._enter("splat")
        sparse = read_sparse_model(ctx.inputs["align"] / "sparse" / "0")
        pts = np.load(ctx.inputs["align"] / "points.npz")
        _write_ply(ctx.work_dir / "point_cloud.ply", pts["xyz"], pts["rgb"])
        self._maybe_fail("splat")
        write_sparse_model(ctx.work_dir / "sparse" / "0", sparse, binary=True)
        return {"train": {"loss": {"first": 1.0, "last": 0.5, "count": int(ctx.settings.train.iters)}}}

    def render(self, ctx: StageContext):
        self._enter("render")
        sparse = read_sparse_model(ctx.inputs["sparse"] / "0")
        colour = _read_ply_rgb(ctx.inputs["scene"]).mean(axis=0)
        out = {}
        for name in sparse.names:
            cam = sparse.camera_of(name)
            out[name.rsplit(".", 1)[0]] = np.broadcast_to(colour, (cam.height, cam.width, 3)).copy()
        write_views(ctx.work_dir / "renders", out)
        return {"views": list(out)}

    def select(self, ctx: StageContext):
        self._enter("select")
        images = read_views(ctx.inputs["images"])
        k = ctx.settings.views
        sharp = {n: float(cv2.Laplacian(cv2.cvtColor(v, cv2.COLOR_RGB2GRAY), cv2.CV_32F).var())
                 for n, v in images.items()}
        names = sorted(sorted(sharp, key=sharp.get, reverse=True)[:k]) if ctx.settings.select_views \
            else list(images)
        (ctx.work_dir / "selection.json").write_text(json.dumps({"names": names}))
        return {"selected": names}

    def refine(self, ctx: StageContext):
        self._enter("refine")
        names = json.loads(ctx.inputs["selection"].read_text())["names"]
        noisy = read_views(ctx.inputs["noisy"], names)
        renders = read_views(ctx.inputs["renders"], names)
        out = {n: 0.8 * cv2.GaussianBlur(noisy[n], (0, 0), 1.0) + 0.2 * renders[n] for n in names}
        write_views(ctx.work_dir / "denoised", out)
        (ctx.work_dir / "n2v_model.pt").write_text(json.dumps({"refined_from": ctx.inputs["model"].name}))
        return {"views": names, "round2": {"reverted": self.refine_keeps_previous, "loss_before": 0.0125,
                                           "loss_after": 0.0131 if self.refine_keeps_previous else 0.0120}}

    def fuse(self, ctx: StageContext):
        self._enter("fuse")
        denoised = read_views(ctx.inputs["images"])
        noisy = read_views(ctx.inputs["noisy"], list(denoised))
        write_views(ctx.work_dir / "noisy_renders", noisy)
        write_views(ctx.work_dir / "fused", {k: 0.5 * (denoised[k] + noisy[k]) for k in denoised})
        return {"views": list(denoised)}

    def stages(self) -> PipelineStages:
        return PipelineStages(denoise=self.denoise, align=self.align, splat=self.splat, render=self.render,
                              select=self.select, refine=self.refine, fuse=self.fuse)

    def spied(self, name: str, record) -> tuple[PipelineStages, list]:
        """(the stages with stage `name` wrapped, the list it fills): each call appends `record(ctx)`, then
        runs the stage."""
        seen: list = []
        stage = getattr(self, name)

        def spy(ctx: StageContext):
            seen.append(record(ctx))
            return stage(ctx)

        return dataclasses.replace(self.stages(), **{name: spy}), seen


def tiny_dataset(root: Path):
    """A 6-view `DatasetFolder` (`make_scene` images as both noisy and clean, a PINHOLE camera, views 0.1
    apart along x, 30 random points) with view 0 held out."""
    from eval.pipeline.validate import DatasetFolder

    images = make_scene(root / "images", n=6)
    files = {p.stem: p for p in sorted(images.glob("*.png"))}
    names = sorted(files)
    cam = Camera("PINHOLE", 48, 40, [50.0, 50.0, 24.0, 20.0])
    posed = [PosedImage(f"{n}.png", 1, np.hstack([np.eye(3), [[-0.1 * i], [0.0], [0.0]]]))
             for i, n in enumerate(names)]
    rng = np.random.default_rng(0)
    write_sparse_model(root / "sparse" / "0", SparseModel({1: cam}, posed, rng.normal(size=(30, 3)) + [0, 0, 4],
                                                          (rng.random((30, 3)) * 255).astype(np.uint8)), binary=True)
    (root / "split.json").write_text(json.dumps({"train": names[1:], "test": names[:1]}))
    return DatasetFolder(root=root, train=names[1:], test=names[:1], images=files, clean=files)
