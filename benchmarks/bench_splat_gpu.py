"""Splatting on CUDA: our torch rasterizer next to gsplat 1.5.3 on the same scene, and our CPU path.

Forward + backward of one view, the work of one training iteration, with about 55k Gaussians at
256x192 and 504x378 (the sizes of issue 24). The scene is a random cloud of Gaussians 3 units in front
of the camera (`tests/splat/scenes.py`), SH degree 3, float32. Each timing is the median of 10 runs
after 3 warm-ups, with `torch.cuda.synchronize()` around each run. Both renderers get identical
activated parameters; the table also gives the largest colour difference between the two images.

Rows:
- ours, torch backend, CUDA: `splat.rasterize(..., config=RasterConfig(backend="torch"))`;
- gsplat 1.5.3, CUDA: `gsplat.rasterization(..., packed=False)` (its fused CUDA kernels);
- ours, C++ compositor, CPU of the same machine, 2 threads: the path this project's 2-core users run
  (the CPU here is not the 2-core machine of the other sections: compare within this table only).

Needs CUDA and gsplat (`pip install gsplat==1.5.3`, which JIT-compiles its kernels on first use);
without them the script writes nothing and exits 0 with a message.

Run: `python benchmarks/bench_splat_gpu.py [--out DIR]` (writes DIR/splat_gpu.md, default docs/bench).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import torch  # noqa: E402
from _common import ROOT, md_table  # noqa: E402

from splat.rasterize import RasterConfig, rasterize  # noqa: E402
from tests.splat.scenes import activated, random_camera, random_scene  # noqa: E402

N_GAUSSIANS = 55_000
SIZES = ((256, 192), (504, 378))


def _time(fn, *, cuda: bool, repeat: int = 10, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        if cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    times.sort()
    return times[len(times) // 2]


def _leaves(params, device):
    return [p.detach().to(device=device, dtype=torch.float32).clone().requires_grad_(True) for p in params]


def _ours(params, cam, K, w, h, backend, threads=None):
    def step():
        means, quats, scales, opac, sh = _leaves(params, cam.device)
        out = rasterize(means, quats, scales, opac, sh, cam, K, w, h, sh_degree=3,
                        config=RasterConfig(backend=backend, num_threads=threads))
        (out.rgb.sum() + out.alpha.sum()).backward()
        return out
    return step


def _gsplat(gsplat, params, cam, K, w, h):
    def step():
        means, quats, scales, opac, sh = _leaves(params, cam.device)
        rgb, alpha, _ = gsplat.rasterization(means, quats, scales, opac, sh, cam[None], K[None], w, h,
                                             sh_degree=3, packed=False)
        (rgb.sum() + alpha.sum()).backward()
        return rgb, alpha
    return step


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "bench")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("bench_splat_gpu: no CUDA device; nothing measured")
        return 0
    try:
        import gsplat
    except ImportError:
        print("bench_splat_gpu: gsplat is not installed (pip install gsplat==1.5.3); nothing measured")
        return 0
    dev = torch.device("cuda")
    params = activated(random_scene(N_GAUSSIANS, seed=7, dtype=torch.float32, spread=1.0, scale_range=(0.005, 0.03)))
    rows = []
    for w, h in SIZES:
        cam, K = random_camera(w, h, seed=3, dtype=torch.float32)
        cam_d, K_d = cam.to(dev), K.to(dev)
        ours_gpu = _ours(params, cam_d, K_d, w, h, "torch")
        ref_gpu = _gsplat(gsplat, params, cam_d, K_d, w, h)
        out = ours_gpu()
        ref_rgb, ref_alpha = ref_gpu()
        diff = (out.rgb.detach().permute(1, 2, 0) - ref_rgb[0].detach()).abs().max().item()
        t_ours = _time(ours_gpu, cuda=True)
        t_ref = _time(ref_gpu, cuda=True)
        t_cpu = _time(_ours(params, cam, K, w, h, "cpp", threads=2), cuda=False, repeat=3, warmup=1)
        rows.append([f"{w}x{h}", N_GAUSSIANS, out.num_intersections, f"{t_ours * 1e3:.1f}", f"{t_ref * 1e3:.2f}",
                     f"{t_ours / t_ref:.0f}x", f"{t_cpu * 1e3:.0f}", f"{diff:.1e}"])
        print(rows[-1], flush=True)
    gpu = torch.cuda.get_device_name(0)
    body = (
        f"Machine: {gpu}, torch {torch.__version__}, gsplat {gsplat.__version__}, Python "
        f"{platform.python_version()}; CPU row on the same machine's CPU with 2 compositor threads.\n"
        f"Reproduce: `python benchmarks/bench_splat_gpu.py` on a CUDA machine with gsplat 1.5.3.\n\n"
        + md_table(["size", "Gaussians", "tile-Gaussian pairs", "ours, CUDA (ms)", "gsplat, CUDA (ms)",
                    "ours / gsplat", "ours, C++ CPU 2 threads (ms)", "max colour diff vs gsplat"], rows)
        + "\nForward + backward of one view (one training iteration's rendering work), median of 10.\n"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "splat_gpu.md"
    path.write_text("## Gaussian splatting on CUDA, next to gsplat\n\n" + body)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
