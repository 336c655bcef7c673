"""The C++ compositor's speed on real-size views: this checkout's kernels against a base commit's, in one process.

Two libraries are compiled and loaded side by side: this checkout's kernels, and the same kernels with the
base commit's `splat/csrc/composite.cpp` in place of this checkout's, built with the base's flags (its
`splat/_cpu_kernel.py`), so that only the compositor differs. `splat._cpu_kernel`'s library handle is
switched between them, view by view, so both see the same machine load. Input: a trained splat and its
cameras, a pipeline round folder with `point_cloud.ply` and
`sparse/0` (for example the real-size run of `benchmarks/bench_pipeline_speed.py --configs=default:504x378:17`).
Two measurements, each over every view, `--rounds` times:

1. the compositing kernels alone (`_cpu_kernel.forward` and `backward`) on each view's projected Gaussians
   (random colours and depth: four channels, as the trainer's);
2. one training step as `splat.train` takes it (render with SH degree 3, the L1 + SSIM loss, backward), so the
   share of the compositor in a step is seen.

The largest differences between the versions' outputs are reported relative to each output's largest value: a
faster path must give the same images and gradients up to float round-off. A diagnostic, not part of `make
bench`: it compares against a chosen commit.

Usage: .venv/bin/python benchmarks/diag_composite_speed.py --run ROUND_DIR [--base REF] [--rounds N]
           [--threads T] [--page NAME]   (writes docs/bench/composite_speed.md, or NAME.md)
"""

from __future__ import annotations

import argparse
import ast
import ctypes
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, cpu_model, md_table, write_fragment  # noqa: E402

DEFAULT_BASE = "1f82df1"  # the scalar per-pixel compositor


def _flags(kernel_py: str) -> list[str]:
    match = re.search(r"^_FLAGS = (\[.*?\])$", kernel_py, re.M)
    if match is None:
        raise SystemExit("no _FLAGS list in the base's splat/_cpu_kernel.py")
    return ast.literal_eval(match.group(1))


def build(csrc: Path, flags: list[str], out: Path) -> ctypes.CDLL:
    """Compile the kernels of `csrc` with `flags` into `out` and load them, checked against this checkout's
    signature table (`splat._cpu_kernel.check_library`)."""
    from splat import _cpu_kernel as ck

    sources = [str(csrc / src.name) for src in ck._SOURCES]
    cxx = ck._compiler()
    if cxx is None:
        raise SystemExit("no C++ compiler found (g++, or set CXX)")
    subprocess.run([cxx, *flags, f"-I{csrc}", *sources, "-o", str(out)], check=True)
    lib = ctypes.CDLL(str(out))
    ck.check_library(lib)
    return lib


def base_kernels(ref: str, work: Path) -> ctypes.CDLL:
    """This checkout's kernels with the base commit's compositor (extracted with `git archive`), built with the
    base's flags."""
    tar = subprocess.run(["git", "archive", ref, "splat/csrc/composite.cpp", "splat/_cpu_kernel.py"], cwd=ROOT,
                         check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(work)], input=tar, check=True)
    flags = _flags((work / "splat" / "_cpu_kernel.py").read_text())
    csrc = work / "csrc"
    shutil.copytree(ROOT / "splat" / "csrc", csrc)
    shutil.copy(work / "splat" / "csrc" / "composite.cpp", csrc / "composite.cpp")
    return build(csrc, flags, work / "base.so")


def load_views(run: Path):
    """The trained Gaussians (`point_cloud.ply`) and the round's cameras (`sparse/0`): model, [(cam_from_world,
    K)], width, height."""
    import torch

    from mvgeo.sparse_model import read_sparse_model
    from splat.cameras_torch import pinhole_K
    from splat.ply import read_gaussian_ply

    model = read_gaussian_ply(run / "point_cloud.ply")
    sparse = read_sparse_model(run / "sparse" / "0")
    views = [(torch.as_tensor(sparse.image(name).cam_from_world, dtype=torch.float32),
              pinhole_K(sparse.camera_of(name))) for name in sparse.names]
    cam = sparse.camera_of(sparse.names[0])
    return model, views, cam.width, cam.height


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a round folder with point_cloud.ply and sparse/0")
    ap.add_argument("--base", default=DEFAULT_BASE, help="the commit to compare with (default %(default)s)")
    ap.add_argument("--rounds", type=int, default=4, help="passes over the views per measurement, the first a "
                    "warm-up (at least 2)")
    ap.add_argument("--threads", type=int, default=2, help="compositor threads (the trainer's: the cores)")
    ap.add_argument("--page", default="composite_speed", help="docs/bench/NAME.md to write")
    args = ap.parse_args()
    if args.rounds < 2:
        ap.error("--rounds must be at least 2: the first pass over the views is a warm-up")

    import torch

    from splat import _cpu_kernel as ck
    from splat.composite import ALPHA_MAX, TRANSMITTANCE_MIN
    from splat.losses import photometric_loss
    from splat.projection import ALPHA_MIN, project_gaussians
    from splat.rasterize import RasterConfig
    from splat.tiles import bin_gaussians

    torch.set_num_threads(1)  # as the trainer (TrainConfig.torch_threads); the kernels use --threads
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=True, capture_output=True,
                          text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "splat"], cwd=ROOT, check=True, capture_output=True,
                           text=True).stdout.strip()
    this = f"{head}{' + changes' if dirty else ''}"
    model, views, width, height = load_views(args.run)
    load_before = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="composite_speed_") as tmp:
        libs = {"base": base_kernels(args.base, Path(tmp)), "this": ck.load()}
        # 1. The kernels alone.
        inputs = []
        gen = torch.Generator().manual_seed(0)
        with torch.no_grad():
            for cam_from_world, K in views:
                proj = project_gaussians(model.means, model.quats, torch.exp(model.log_scales),
                                         torch.sigmoid(model.opacity_logits).reshape(-1), cam_from_world, K,
                                         width, height)
                bins = bin_gaussians(proj.means2d, proj.extents_px, proj.depths, proj.visible, width, height)
                colours = torch.rand(model.num_gaussians, 4, generator=gen)
                inputs.append((bins, proj.means2d.contiguous(), proj.conics.contiguous(), colours,
                               proj.opacities.contiguous()))
        kernel_s = {k: [0.0, 0.0] for k in libs}
        kernel_out = {}
        for rnd in range(args.rounds):
            for v, (bins, m2, con, col, op) in enumerate(inputs):
                for name, lib in libs.items():
                    ck._lib = lib
                    t0 = time.perf_counter()
                    acc, trans, last = ck.forward(bins, m2, con, col, op, width, height, alpha_min=ALPHA_MIN,
                                                  alpha_max=ALPHA_MAX, transmittance_min=TRANSMITTANCE_MIN,
                                                  num_threads=args.threads)
                    t1 = time.perf_counter()
                    g_acc = torch.full_like(acc, 0.01)
                    g_trans = torch.full_like(trans, 0.01)
                    rows = ck.backward(bins, m2, con, col, op, width, height, trans, last, g_acc, g_trans,
                                       alpha_min=ALPHA_MIN, alpha_max=ALPHA_MAX, num_threads=args.threads)
                    t2 = time.perf_counter()
                    if rnd > 0:  # the first pass warms up
                        kernel_s[name][0] += t1 - t0
                        kernel_s[name][1] += t2 - t1
                    if rnd == 0:
                        kernel_out[(name, v)] = (acc, trans, rows)
        # 2. Training steps.
        target = torch.rand(3, height, width, generator=gen)
        params = list(model.parameters())
        for p in params:
            p.requires_grad_(True)
        raster = RasterConfig(num_threads=args.threads)
        step_s = {k: [0.0, 0.0, 0.0] for k in libs}
        step_out = {}
        for rnd in range(args.rounds):
            for v, (cam_from_world, K) in enumerate(views):
                for name, lib in libs.items():
                    ck._lib = lib
                    model.zero_grad(set_to_none=True)
                    t0 = time.perf_counter()
                    out = model.render(cam_from_world, K, width, height, sh_degree=3,
                                       background=torch.zeros(3), config=raster)
                    t1 = time.perf_counter()
                    loss = photometric_loss(out.rgb, target, ssim_weight=0.2, num_threads=args.threads)
                    t2 = time.perf_counter()
                    loss.backward()
                    t3 = time.perf_counter()
                    if rnd > 0:
                        for i, dt in enumerate((t1 - t0, t2 - t1, t3 - t2)):
                            step_s[name][i] += dt
                    if rnd == 0:
                        step_out[(name, v)] = [out.rgb.detach().clone()] + [p.grad.clone() for p in params]
        ck._lib = libs["this"]
    load_after = " / ".join(f"{x:.1f}" for x in os.getloadavg())

    def rel(a, b):
        return float((a - b).abs().max() / b.abs().max().clamp(min=1e-30))

    n = (args.rounds - 1) * len(views)
    ms = {k: [1e3 * x / n for x in v] for k, v in kernel_s.items()}
    st = {k: [1e3 * x / n for x in v] for k, v in step_s.items()}
    d_fwd = max(max(rel(kernel_out[("this", v)][i], kernel_out[("base", v)][i]) for i in (0, 1))
                for v in range(len(views)))
    d_bwd = max(rel(kernel_out[("this", v)][2], kernel_out[("base", v)][2]) for v in range(len(views)))
    d_rgb = max(rel(step_out[("this", v)][0], step_out[("base", v)][0]) for v in range(len(views)))
    d_grad = max(max(rel(a, b) for a, b in zip(step_out[("this", v)][1:], step_out[("base", v)][1:], strict=True))
                 for v in range(len(views)))
    isect = sum(int(b.gaussian_ids.numel()) for b, *_ in inputs) / len(inputs)
    rows1 = [[what, f"{ms['base'][i]:.1f}", f"{ms['this'][i]:.1f}", f"{ms['this'][i] / ms['base'][i]:.2f}x"]
             for i, what in enumerate(("forward", "backward"))]
    rows1.append(["both", f"{sum(ms['base']):.1f}", f"{sum(ms['this']):.1f}",
                  f"{sum(ms['this']) / sum(ms['base']):.2f}x"])
    rows2 = [[what, f"{st['base'][i]:.1f}", f"{st['this'][i]:.1f}", f"{st['this'][i] / st['base'][i]:.2f}x"]
             for i, what in enumerate(("render (projection, SH, tiles, compositor)", "loss (L1 + SSIM)",
                                       "backward"))]
    rows2.append(["step", f"{sum(st['base']):.1f}", f"{sum(st['this']):.1f}",
                  f"{sum(st['this']) / sum(st['base']):.2f}x"])
    body = (
        f"Input: `{args.run}` ({model.num_gaussians} Gaussians, {len(views)} views at {width}x{height}, "
        f"{isect:.0f} tile intersections per view on average). Base: this checkout with commit `{args.base}`'s "
        f"compositor (`splat/csrc/composite.cpp`, built with that commit's flags); this: `{this}`. "
        f"{args.threads} compositor threads, torch at one thread (the trainer's). Milliseconds per view, mean over "
        f"{args.rounds - 1} passes over the views after a warm-up pass, the "
        f"two versions alternating view by view. Machine: {cpu_model()}, load (1/5/15 min) {load_before} at the "
        f"start, {load_after} at the end.\n\n"
        "The compositing kernels alone:\n\n" + md_table(["kernel", "base (ms)", "this (ms)", "time ratio"], rows1)
        + "\nOne training step (`splat.train`'s render, loss and backward; SH degree 3):\n\n"
        + md_table(["part", "base (ms)", "this (ms)", "time ratio"], rows2)
        + f"\nLargest differences between the versions, relative to the output's largest value: forward image and "
        f"transmittance {d_fwd:.1e}, backward rows {d_bwd:.1e}; training step's image {d_rgb:.1e}, parameter "
        f"gradients {d_grad:.1e}.\n")
    cmd = (f"`.venv/bin/python benchmarks/diag_composite_speed.py --run {args.run} --base {args.base} "
           f"--rounds {args.rounds} --threads {args.threads}`")
    print(body)
    path = write_fragment(args.page, "The compositor's speed on real-size views (this checkout against a base "
                          "commit)", body, reproduce=cmd)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
