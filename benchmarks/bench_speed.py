"""Splat training-iteration speed: where one iteration's time goes, and the C++ path against the torch one.

1. Profile (`--profile` runs only this part): one training iteration at 504x378 with ~55k Gaussians
   (a random scene, and the trainer's initial Gaussians on `llff_like_clean`) split
   into activations, projection, SH colour, tile binning, compositing forward, loss (L1 + SSIM) forward
   and backward, compositing backward, SH backward, projection backward and the fused Adam step. The
   graph is cut between stages (each stage's outputs become fresh leaves), so every backward is timed
   alone; the sum matches a whole iteration to within the overhead of the cuts.
2. Forward + backward per iteration at 256x192 and 504x378 with ~55k Gaussians, three paths in the
   same run:
   - "cpp": `RasterConfig(backend="cpp")`, projection, binning, SH and compositor in C++, and the fused
     C++ L1 + SSIM loss (`splat/csrc/ssim.cpp`; its "loss forward" computes the gradient too);
   - "torch proj+bin": torch projection and binning (the reference) with the C++ SH, compositor and loss;
   - "torch": the all-torch reference, loss included (256x192 only: its compositor takes seconds per
     iteration).
3. A short training run (InstantSplat-style, ground-truth poses, 12 views of `llff_like_clean` at
   128x96, 300 iterations) with `backend="cpp"` and `backend="torch"`: held-out PSNR of each.

Threads as in the trainer: torch single-threaded, C++ kernels 2 threads. The random scene is uniform
in a 3 x 3 x 2 box 3 units in front of the camera, scales log-uniform in 5-50 mm; the intersection
count is stated next to the times.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
import torch  # noqa: E402
from _common import first_train_views, md_table, write_fragment  # noqa: E402

from splat.composite import composite_tiles  # noqa: E402
from splat.losses import photometric_loss  # noqa: E402
from splat.projection import project_gaussians  # noqa: E402
from splat.rasterize import RasterConfig, rasterize  # noqa: E402
from splat.sh import eval_sh_fast  # noqa: E402
from splat.tiles import bin_gaussians  # noqa: E402
from tests.splat.scenes import look_at_cam_from_world  # noqa: E402

KERNEL_THREADS = 2
N_GAUSSIANS = 55_000
SIZES = [(256, 192), (504, 378)]


def _load() -> str:
    return " / ".join(f"{x:.1f}" for x in os.getloadavg())


def _lscpu() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
    except OSError:
        return "lscpu unavailable"
    keep = ("Model name", "CPU(s)", "Thread(s) per core", "L3 cache")
    lines = [ln.split(":", 1) for ln in out.splitlines() if ":" in ln]
    return "; ".join(f"{k.strip()}: {v.strip()}" for k, v in lines if k.strip() in keep)


def make_scene(n: int, width: int, height: int, seed: int = 0):
    """Pre-activation leaves (means, quats, log_scales, opacity_logits, sh (n, 16, 3)), camera, K, target."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([3.0, 3.0, 2.0])
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.empty(n, 3).uniform_(np.log(0.005), np.log(0.05), generator=g)
    opacity_logits = torch.logit(torch.rand(n, generator=g) * 0.9 + 0.05)
    sh = (torch.rand(n, 16, 3, generator=g) - 0.5) * 0.5
    cam = look_at_cam_from_world([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], dtype=torch.float32)
    f = 1.1 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32)
    target = torch.rand(3, height, width, generator=g)
    return [means, quats, log_scales, opacity_logits, sh], cam, K, target


def trainer_scene(tmp: Path, width: int = 504, height: int = 378, stride_px: int = 8):
    """The trainer's initial Gaussians on `llff_like_clean` (all 17 training views, points back-projected
    from the ground-truth depth every `stride_px` px: ~51k at 504x378), seen from the first view."""
    from data_synth import render_scene
    from splat.cameras_torch import pinhole_K
    from splat.dataset import load_views, points_from_depth
    from splat.gaussian_model import GaussianModel

    data = tmp / f"llff_{width}"
    render_scene("llff_like_clean", data, size_wh=(width, height))
    views = load_views(data, split="train")
    xyz, rgb = points_from_depth(data, views, stride_px=stride_px)
    model = GaussianModel.from_points(xyz, rgb, sh_degree=3)
    leaves = [t.detach().clone() for t in (model.means, model.quats, model.log_scales, model.opacity_logits,
                                           model.sh)]
    cam = torch.as_tensor(views.cam_from_world[0], dtype=torch.float32)
    target = torch.as_tensor(np.ascontiguousarray(views.images[0], dtype=np.float32)).permute(2, 0, 1)
    return leaves, cam, pinhole_K(views.cameras[0]), target


def _cfg(backend: str) -> RasterConfig:
    return RasterConfig(backend=backend, num_threads=KERNEL_THREADS)


def iteration(leaves, cam, K, target, width, height, path: str) -> int:
    """Forward + backward of one training iteration (activations, render, loss); returns intersections."""
    for p in leaves:
        p.grad = None
    means, quats, log_scales, opacity_logits, sh = leaves
    scales, opac = torch.exp(log_scales), torch.sigmoid(opacity_logits)
    if path in ("cpp", "torch"):
        out = rasterize(means, quats, scales, opac, sh, cam, K, width, height, sh_degree=3, config=_cfg(path))
        rgb, inter = out.rgb, out.num_intersections
    else:  # "torch proj+bin": the reference projection and binning, C++ SH and compositor
        proj = project_gaussians(means, quats, scales, opac, cam, K, width, height, backend="torch")
        centre = -(cam[:3, :3].T @ cam[:3, 3])
        rgb_g = torch.clamp_min(eval_sh_fast(3, sh, means - centre) + 0.5, 0.0)
        feats = torch.cat([rgb_g, proj.depths[:, None]], -1)
        bins = bin_gaussians(proj.means2d, proj.extents_px, proj.depths, proj.visible, width, height,
                             backend="torch")
        accum, _ = composite_tiles(proj.means2d, proj.conics, feats, proj.opacities, bins, width, height,
                                   backend="cpp", num_threads=KERNEL_THREADS)
        rgb, inter = accum[..., :3].permute(2, 0, 1), int(bins.gaussian_ids.numel())
    loss_backend = "torch" if path == "torch" else "cpp"
    photometric_loss(rgb, target, backend=loss_backend, num_threads=KERNEL_THREADS).backward()
    return inter


def profile(scene, width: int = 504, height: int = 378, repeat: int = 5) -> tuple[list[list[object]], float, int]:
    """Per-stage times (median of `repeat` iterations) of the C++ path; see the module docstring."""
    leaves, cam, K, target = scene
    leaves = [p.detach().clone().requires_grad_(True) for p in leaves]
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3} for p in leaves], eps=1e-15, fused=True)
    names = ["activations", "projection", "SH colour", "tile binning", "composite forward",
             "loss forward (L1 + SSIM)", "loss backward", "composite backward", "SH backward",
             "projection + activations backward", "Adam step (fused)"]
    samples: dict[str, list[float]] = {k: [] for k in names}
    totals, inter = [], 0

    def cut(*tensors):
        return [t.detach().requires_grad_(True) for t in tensors]

    for it in range(repeat + 1):
        t: dict[str, float] = {}
        start = time.perf_counter()
        clock = [start]

        def lap(name, t=t, clock=clock):
            now = time.perf_counter()
            t[name] = now - clock[0]
            clock[0] = now

        for p in leaves:
            p.grad = None
        means, quats, log_scales, opacity_logits, sh = leaves
        scales, opac = torch.exp(log_scales), torch.sigmoid(opacity_logits)
        lap("activations")
        proj = project_gaussians(means, quats, scales, opac, cam, K, width, height, backend="cpp",
                                 num_threads=KERNEL_THREADS)
        lap("projection")
        centre = -(cam[:3, :3].T @ cam[:3, 3])
        rgb_g = torch.clamp_min(eval_sh_fast(3, sh, means - centre) + 0.5, 0.0)
        lap("SH colour")
        bins = bin_gaussians(proj.means2d, proj.extents_px, proj.depths, proj.visible, width, height, backend="cpp")
        lap("tile binning")
        m2, con, dep, op, col = cut(proj.means2d, proj.conics, proj.depths, proj.opacities, rgb_g)
        accum, _ = composite_tiles(m2, con, torch.cat([col, dep[:, None]], -1), op, bins, width, height,
                                   backend="cpp", num_threads=KERNEL_THREADS)
        lap("composite forward")
        (rgb,) = cut(accum[..., :3].permute(2, 0, 1))
        loss = photometric_loss(rgb, target, backend="cpp", num_threads=KERNEL_THREADS)
        lap("loss forward (L1 + SSIM)")
        loss.backward()
        lap("loss backward")
        accum[..., :3].permute(2, 0, 1).backward(rgb.grad)
        lap("composite backward")
        rgb_g.backward(col.grad)
        lap("SH backward")
        torch.autograd.backward([proj.means2d, proj.conics, proj.depths, proj.opacities],
                                [m2.grad, con.grad, dep.grad, op.grad])
        lap("projection + activations backward")
        opt.step()
        lap("Adam step (fused)")
        if it == 0:
            continue  # warm-up (kernel load, allocator)
        inter = int(bins.gaussian_ids.numel())
        totals.append(time.perf_counter() - start)
        for k in names:
            samples[k].append(t[k])
    med = {k: float(np.median(v)) for k, v in samples.items()}
    total = float(np.median(totals))
    rows = [[k, f"{1000 * med[k]:.1f}", f"{100 * med[k] / sum(med.values()):.0f}%"] for k in names]
    return rows, total, inter


def split_summary(rows: list[list[object]]) -> str:
    """One sentence: the shares of compositing, loss and projection + binning in the profile rows."""
    ms = {str(r[0]): float(r[1]) for r in rows}
    total = sum(ms.values())

    def share(*names):
        return f"{100 * sum(ms[n] for n in names) / total:.0f}%"

    return (f"Compositing forward + backward take {share('composite forward', 'composite backward')} of the "
            f"iteration, the L1 + SSIM loss {share('loss forward (L1 + SSIM)', 'loss backward')}, projection + "
            "tile binning (forward and backward) "
            f"{share('projection', 'tile binning', 'projection + activations backward')}, "
            f"SH {share('SH colour', 'SH backward')}, the Adam step {share('Adam step (fused)')}.")


def bench_paths(rows, trainer):
    cases = [("random", w, h, make_scene(N_GAUSSIANS, w, h)) for w, h in SIZES]
    cases.append(("llff_like init", 504, 378, trainer))
    for scene_name, width, height, (leaves, cam, K, target) in cases:
        leaves = [p.detach().clone().requires_grad_(True) for p in leaves]
        paths = ["cpp", "torch proj+bin"] + (["torch"] if width <= 256 else [])
        # Paths interleaved, repeat by repeat, so that a change of the machine's load hits all of them alike.
        iteration(leaves, cam, K, target, width, height, "cpp")  # warm-up (kernel load)
        samples: dict[str, list[float]] = {p: [] for p in paths}
        for rep in range(7):
            for path in paths:
                if path == "torch" and rep >= 1:
                    continue  # seconds per iteration: one sample
                start = time.perf_counter()
                inter = iteration(leaves, cam, K, target, width, height, path)
                samples[path].append(time.perf_counter() - start)
        times = {p: float(np.median(v)) for p, v in samples.items()}
        for path in paths:
            rows.append([scene_name, len(leaves[0]), f"{width}x{height}", path, f"{times[path]:.3f}",
                         f"{times[path] / times['cpp']:.2f}", inter])


def bench_loss(rows, repeat: int = 7) -> None:
    """The L1 + SSIM loss, value and gradient, at both sizes: the torch reference against the C++ kernel."""
    g = torch.Generator().manual_seed(0)
    for width, height in SIZES:
        x = torch.rand(3, height, width, generator=g).requires_grad_(True)
        y = torch.rand(3, height, width, generator=g)
        times: dict[str, list[float]] = {"torch": [], "cpp": []}
        for it in range(repeat + 1):
            for backend in (("torch", "cpp") if it % 2 else ("cpp", "torch")):
                x.grad = None
                start = time.perf_counter()
                photometric_loss(x, y, backend=backend, num_threads=KERNEL_THREADS).backward()
                if it:
                    times[backend].append(time.perf_counter() - start)
        med = {k: float(np.median(v)) for k, v in times.items()}
        rows.append([f"{width}x{height}", f"{1000 * med['torch']:.1f}", f"{1000 * med['cpp']:.1f}",
                     f"{med['torch'] / med['cpp']:.1f}"])


def bench_quality(rows, iters: int = 300, size_wh=(128, 96)):
    from data_synth import render_scene
    from mvgeo.common.imageio import read_image
    from splat.dataset import load_views, points_from_depth
    from splat.render import render_views
    from splat.train import TrainConfig, train_gaussians

    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "llff"
        render_scene("llff_like_clean", data, size_wh=size_wh)
        views = first_train_views(data, 12)
        xyz, rgb = points_from_depth(data, views, stride_px=4)
        test = load_views(data, split="test")
        clean = [read_image(data / "clean" / n) for n in test.names]
        for backend in ("cpp", "torch"):
            t0 = time.perf_counter()
            res = train_gaussians(views.images, views.cameras, views.cam_from_world, xyz, rgb,
                                  TrainConfig(iters=iters, optimize_poses=False, raster=_cfg(backend)))
            elapsed = time.perf_counter() - t0
            outs = render_views(res.model, test.cameras, test.cam_from_world, config=_cfg(backend))
            psnr = float(np.mean([-10 * np.log10(np.mean((o - c) ** 2)) for o, c in zip(outs, clean, strict=True)]))
            rows.append([backend, f"{size_wh[0]}x{size_wh[1]}", iters, len(xyz), f"{elapsed:.1f}", f"{psnr:.3f}"])


def main(argv: list[str]) -> int:
    torch.set_num_threads(1)
    load0 = _load()
    with tempfile.TemporaryDirectory() as tmp:
        trainer = trainer_scene(Path(tmp))
    profiles = []
    for scene_name, scene in (("random", make_scene(N_GAUSSIANS, 504, 378)), ("llff_like init", trainer)):
        rows, total, inter = profile(scene)
        profiles.append((scene_name, len(scene[0][0]), rows, total, inter))
    prof_text = ""
    for scene_name, n, rows, total, inter in profiles:
        prof_text += (f"**{scene_name}** ({n} Gaussians): whole iteration {total:.3f} s, {inter} tile "
                      f"intersections.\n\n" + md_table(["stage", "ms", "share"], rows) + f"\n{split_summary(rows)}\n\n")
    if "--profile" in argv:
        print(prof_text)
        print(f"load {load0} -> {_load()}")
        return 0
    path_rows: list[list[object]] = []
    bench_paths(path_rows, trainer)
    loss_rows: list[list[object]] = []
    bench_loss(loss_rows)
    quality_rows: list[list[object]] = []
    bench_quality(quality_rows)
    body = (
        f"Machine: {_lscpu()}; 2 cores available to this project and shared with other engineers' jobs, "
        f"load average (1/5/15 min) {load0} at the start and {{load1}} at the end; run under `nice`. "
        f"torch {torch.__version__} single-threaded, C++ kernels {KERNEL_THREADS} threads (as the trainer). "
        f"Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Times are wall-clock medians; with the "
        "machine loaded they are upper bounds, compare the ratios measured in the same run.\n\n"
        "### Where one iteration goes (504x378, SH degree 3, C++ path)\n\n"
        "Two scenes (benchmarks/bench_speed.py): `random` (uniform in a box, opacities 0.05-0.95) and "
        "`llff_like init` (the trainer's initial Gaussians on `llff_like_clean`: opacity 0.1, "
        "nearest-neighbour scales), seen from a training view.\n\n" + prof_text +
        f"\n### Forward + backward per iteration, {N_GAUSSIANS} Gaussians\n\n"
        "Activations, render (SH degree 3), L1 + SSIM loss and backward; no optimizer step. "
        "`torch proj+bin`: torch projection and tile binning with the C++ SH, compositor and loss.\n\n"
        + md_table(["scene", "Gaussians", "size", "path", "s / iteration", "ratio to cpp", "intersections"],
                   path_rows) +
        "\n### The L1 + SSIM loss: value and gradient\n\n"
        "`photometric_loss(..., backend=...)` forward + backward on a random image pair: the torch reference "
        f"(torch single-threaded) against the fused C++ kernel ({KERNEL_THREADS} threads).\n\n"
        + md_table(["size", "torch ms", "C++ ms", "ratio"], loss_rows) +
        "\n### Quality: the same short training with each path\n\n"
        "`llff_like_clean`, 12 training views, ground-truth poses, no densification; held-out PSNR "
        "against the clean test views.\n\n"
        + md_table(["backend", "size", "iterations", "Gaussians", "train s", "held-out PSNR dB"], quality_rows)
    )
    body = body.replace("{load1}", _load())
    path = write_fragment("speed", "Splat iteration speed (speed)", body)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
