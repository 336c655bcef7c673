"""data_synth benchmark: rays/s, seconds per 504x378 view, the cost of supersampling,
and how many SIFT matches the built-in scenes give (texture sufficiency).

Run: .venv/bin/python benchmarks/bench_data_synth.py   (writes docs/bench/data_synth.md)
Uses no data from ../shared/data (scenes are procedural).
"""

from __future__ import annotations

import os
import platform
import time

import numpy as np
from _common import md_table, peak_rss_mb, time_call, write_fragment

from data_synth import SceneRenderer, load_scene, rig_views
from data_synth.effects import EffectContext, apply_effects, effects_need
from data_synth.intrinsics import camera_from_spec, camera_rays, sample_positions
from mvgeo.common.deps import cv2
from mvgeo.common.imageio import to_uint

SIZE = (504, 378)


def _sift_matches(img_a: np.ndarray, img_b: np.ndarray) -> int:
    """Matches passing Lowe's ratio test (0.8) and a RANSAC fundamental-matrix check."""
    sift = cv2.SIFT_create()
    ka, da = sift.detectAndCompute(cv2.cvtColor(to_uint(img_a), cv2.COLOR_RGB2GRAY), None)
    kb, db = sift.detectAndCompute(cv2.cvtColor(to_uint(img_b), cv2.COLOR_RGB2GRAY), None)
    if da is None or db is None or len(ka) < 8 or len(kb) < 8:
        return 0
    pairs = cv2.BFMatcher().knnMatch(da, db, k=2)
    good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < 0.8 * n.distance]
    if len(good) < 8:
        return len(good)
    pa = np.float32([ka[m.queryIdx].pt for m in good])
    pb = np.float32([kb[m.trainIdx].pt for m in good])
    _, inliers = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 1.0, 0.999)
    return int(inliers.sum()) if inliers is not None else 0


def _cpu_s(fn, *, repeat: int = 3) -> float:
    """Median process CPU time (all threads) of fn(): robust to other jobs on a shared machine."""
    times = []
    for _ in range(repeat):
        t = time.process_time()
        fn()
        times.append(time.process_time() - t)
    return sorted(times)[len(times) // 2]


def main() -> None:
    load_start = os.getloadavg()
    spec = load_scene("llff_like", size_wh=SIZE)
    t0 = time.perf_counter()
    renderer = SceneRenderer.from_spec(spec)
    setup_s = time.perf_counter() - t0
    camera = camera_from_spec(spec.camera, SIZE)
    views = rig_views(spec.rig)
    pose = views[0].cam_from_world

    # Ray casting alone (Embree through open3d), 2x2 supersampling worth of rays.
    uv = sample_positions(SIZE, 2).reshape(-1, 2)
    dirs, _ = camera_rays(camera, uv)
    R = pose[:, :3]
    centre = -R.T @ pose[:, 3]
    dirs_world = dirs @ R
    n_rays = dirs_world.shape[0]
    cast_s = time_call(lambda: renderer.cast(centre, dirs_world, normals=False), repeat=5)
    cast_cpu = _cpu_s(lambda: renderer.cast(centre, dirs_world, normals=False), repeat=5)
    cast_n_s = time_call(lambda: renderer.cast(centre, dirs_world, normals=True), repeat=5)

    rows = []
    per_view = {}
    per_view_cpu = {}
    for n in (1, 2, 3):
        def job(n=n):
            return renderer.render(camera, pose, supersample=n, depth=True)

        s = time_call(job, repeat=3)
        c = _cpu_s(job)
        per_view[n], per_view_cpu[n] = s, c
        rays = SIZE[0] * SIZE[1] * n * n
        rows.append([f"{n}x{n}", rays, s, c, rays / s / 1e6, s / per_view[1]])

    # Effects of llff_like (gaussian sigma 25/255) and PNG encoding, per view.
    r = renderer.render(camera, pose, supersample=2, depth=True)
    ctx = EffectContext(view_name=views[0].name, K=camera.K, depth=r.depth)
    effects_s = time_call(lambda: apply_effects(r.rgb, spec.effects, seed=0, ctx=ctx), repeat=5)
    png_s = time_call(lambda: cv2.imencode(".png", to_uint(r.rgb)[:, :, ::-1].copy()), repeat=5)

    # Texture sufficiency: SIFT matches between neighbouring views (clean and as degraded).
    sift_rows = []
    for name in ("llff_like", "object_ring", "hard_lowtexture", "hard_repetitive", "hard_tinybaseline",
                 "hard_highnoise", "poisson"):
        sp = load_scene(name, size_wh=SIZE)
        rend = SceneRenderer.from_spec(sp)
        cam = camera_from_spec(sp.camera, SIZE)
        vs = rig_views(sp.rig)[:2]
        imgs = [rend.render(cam, v.cam_from_world, supersample=sp.render.supersample,
                            depth="depth" in effects_need(sp.effects)) for v in vs]
        clean = [im.rgb for im in imgs]
        degraded = [apply_effects(im.rgb, sp.effects, seed=sp.info.seed,
                                  ctx=EffectContext(v.name, cam.K, im.depth)) for im, v in zip(imgs, vs, strict=True)]
        sift_rows.append([name, _sift_matches(*clean), _sift_matches(*degraded)])

    load_end = os.getloadavg()
    body = (
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, **shared with other engineers' jobs** "
        f"(load average {load_start[0]:.1f} at start, {load_end[0]:.1f} at end), so absolute times are "
        "pessimistic; ratios within this run are comparable.\n\n"
        f"Scene `llff_like` (10 objects, {sum(len(m.triangles) for m in renderer.meshes)} triangles), "
        f"{SIZE[0]}x{SIZE[1]}, depth output on. Scene setup (meshes + Embree BVH): {setup_s:.2f} s.\n\n"
        "### Per view\n\n"
        + md_table(["supersampling", "rays", "wall s / view", "CPU s / view (all threads)", "Mrays/s (wall)",
                    "wall cost vs 1x1"], rows)
        + "\n"
        + md_table(["stage", "wall seconds"], [
            [f"ray casting only, {n_rays} rays (2x2)", cast_s],
            ["ray casting only, CPU seconds (all threads)", cast_cpu],
            ["ray casting + shading normals", cast_n_s],
            ["Embree rays/s (casting only, wall)", f"{n_rays / cast_s / 1e6:.2f} M"],
            ["effects (gaussian) per view", effects_s],
            ["PNG encode per image", png_s],
        ])
        + f"\nTarget: under 1 s per 504x378 view with 2x2 supersampling on 2 cores. Measured: "
        f"{per_view[2]:.2f} s wall ({'met' if per_view[2] < 1.0 else 'NOT met'} on this shared machine), "
        f"{per_view_cpu[2]:.2f} CPU-seconds (summed over threads; an idle 2-core machine needs at most that "
        "much wall time, less where OpenCV/Embree run in parallel). "
        f"Ray casting is {100 * cast_cpu / per_view_cpu[2]:.0f}% of the 2x2 render's CPU time; the rest is "
        "procedural texture evaluation (noise-volume lookups at every ray hit) and shading. Everything scales "
        f"with the number of rays: in CPU time 2x2 costs {per_view_cpu[2] / per_view_cpu[1]:.1f}x and 3x3 "
        f"{per_view_cpu[3] / per_view_cpu[1]:.1f}x a 1x1 render (wall ratios above are distorted by the "
        "shared machine).\n\n"
        "### SIFT matches between views 0 and 1 (ratio test 0.8 + RANSAC F inliers, 504x378)\n\n"
        + md_table(["scene", "clean", "degraded (as the pipeline sees it)"], sift_rows)
        + f"\nPeak RSS: {peak_rss_mb():.0f} MiB.\n"
    )
    path = write_fragment("data_synth", "data_synth: rendering speed", body)
    print(path.read_text())


if __name__ == "__main__":
    main()
