"""The denoiser's speed on real-size photos: this checkout against a base commit, in one run.

Times what the pipeline's denoise stage does (`denoise.self_supervised.train_with_method`, then
`denoise_with_method`, under the stage's fixed torch thread count) on the 12 noisy training photos of a
dataset: R2R training steps of the `default` preset's UNet (width 16) and the `best` preset's (width 32), and
the 8-pass inference over the 12 photos; with `--tasks dct,grouped`, the two Wiener steps. The base commit's
files are extracted with `git archive` into a temporary folder (the repository's history is needed; nothing is
registered in it); the two code versions run as separate processes, alternating, `--repeats` times, so both
see the same machine load. A diagnostic, not part of `make bench`: it compares against a chosen commit. With
`--quality` both versions also train the `default` network for its full 2000 steps (seed 0) and the photos are
scored against `clean/` (PSNR, SSIM): a faster path must give the same photos up to float round-off.

Without a dataset argument the DTU scan24 photos of `../shared/data` are imported (12 training views, sigma
25/255, seed 0) into a temporary folder; without `../shared/data` the built-in `llff_like` scene is rendered
at 384x288 (the benchmark then says so).

Usage: .venv/bin/python benchmarks/diag_denoise_speed.py [--dataset DIR] [--base REF] [--repeats N]
           [--steps S] [--quality] [--tasks train,infer,dct,grouped] [--page NAME]
           (writes docs/bench/denoise_speed.md, or NAME.md)
       .venv/bin/python benchmarks/diag_denoise_speed.py --worker DATASET TASK   (one measurement, JSON)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]  # not from _common: that puts this checkout on sys.path
DEFAULT_BASE = "35970c1"  # the commit before the UNet's channels-last fast path
SHARED = ROOT.parent / "shared" / "data"


def worker(dataset: Path, task: str) -> dict:
    """One measurement in this process, with the code on sys.path: `train:WIDTH:STEPS`, `infer:WIDTH`
    or `quality` (2000 steps of the default network, seed 0, scored)."""
    from dataclasses import replace

    import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
    from eval.pipeline import preset
    from eval.pipeline.stage_settings import n2v_config
    from eval.pipeline.views import read_views

    names = [Path(n).stem for n in sorted(json.loads((dataset / "split.json").read_text())["train"])[:12]]
    noisy = read_views(dataset / "images", names)
    images = [noisy[n] for n in names]
    kind, *rest = task.split(":")
    width = int(rest[0]) if rest else 16
    # the denoise stage's network of the `default` (width 16) or `best` (width 32) preset, R2R
    config = replace(n2v_config(preset("default" if width == 16 else "best").denoise), method="r2r")
    assert config.unet.width == width
    try:  # as the denoise stage: one torch thread per piece of work (`denoise.parallel`) ...
        from denoise.parallel import one_thread_per_task as stage_threads
    except ImportError:  # ... or, in code before it, the training's fixed intra-op thread count
        from mvgeo.common.threads import torch_threads

        def stage_threads():
            return torch_threads(config.torch_threads)
    with stage_threads():
        return _measure(kind, rest, config, images, names, dataset)


def _measure(kind: str, rest: list[str], config, images: list, names: list[str], dataset: Path) -> dict:
    from dataclasses import replace

    import numpy as np

    if kind in ("dct", "grouped"):
        return _wiener_step(kind, images, names, dataset)

    from denoise.self_supervised import denoise_with_method, train_with_method
    from eval.pipeline.views import read_views

    if kind == "train":
        config = replace(config, steps=int(rest[1]))
        t0 = time.perf_counter()
        train_with_method(images, config, seed=0)
        return {"seconds": time.perf_counter() - t0, "code": str(Path(sys.modules["denoise"].__file__).parents[1])}
    if kind == "infer":
        model = train_with_method(images, replace(config, steps=2), seed=0)
        t0 = time.perf_counter()
        denoise_with_method(model, images, config, seed=0)
        return {"seconds": time.perf_counter() - t0, "code": str(Path(sys.modules["denoise"].__file__).parents[1])}
    import torch

    from mvgeo.image_metrics import ssim

    t0 = time.perf_counter()
    model = train_with_method(images, config, seed=0)
    out = denoise_with_method(model, images, config, seed=0)
    seconds = time.perf_counter() - t0
    clean = read_views(dataset / "clean", names)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float64))[None]  # noqa: E731
    pairs = list(zip(out, names, strict=True))
    psnr = [float(-10 * np.log10(np.mean((o.astype(np.float64) - clean[n]) ** 2))) for o, n in pairs]
    ssims = [float(ssim(t(o), t(clean[n]))) for o, n in pairs]
    return {"seconds": seconds, "code": str(Path(sys.modules["denoise"].__file__).parents[1]),
            "psnr": float(np.mean(psnr)), "ssim": float(np.mean(ssims)),
            "out": [o.astype(np.float32).tolist() for o in out[:1]]}


def _wiener_step(kind: str, images: list, names: list[str], dataset: Path) -> dict:
    """The DCT (`dct`) or grouped (`grouped`) Wiener step of the 12 photos at sigma 25/255, one photo per
    thread as the denoise stage runs them (`denoise.parallel.run_tasks`); the pilot is each photo's own
    DCT Wiener estimate (the plain empirical Wiener filter, computed before the clock starts). Scored
    against `clean/` (PSNR); the first photo's output is returned for the versions' comparison."""
    import numpy as np

    from denoise.parallel import run_tasks
    from denoise.wiener import dct_wiener
    from eval.pipeline.views import read_views

    sigma = 25.0 / 255.0
    pilots = [np.clip(dct_wiener(y, y, sigma), 0.0, 1.0) for y in images]
    if kind == "dct":
        step = lambda item: dct_wiener(item[0], item[1], sigma)  # noqa: E731
    else:
        from denoise.grouped_wiener import grouped_wiener

        step = lambda item: grouped_wiener(item[0], item[1], sigma)  # noqa: E731
    t0 = time.perf_counter()
    out = run_tasks(step, list(zip(images, pilots, strict=True)))
    seconds = time.perf_counter() - t0
    clean = read_views(dataset / "clean", names)
    psnr = [float(-10 * np.log10(np.mean((np.clip(o, 0, 1).astype(np.float64) - clean[n]) ** 2)))
            for o, n in zip(out, names, strict=True)]
    return {"seconds": seconds, "code": str(Path(sys.modules["denoise"].__file__).parents[1]),
            "psnr": float(np.mean(psnr)), "out": [np.asarray(out[0], np.float32).tolist()]}


def _dataset(arg: Path | None, tmp: Path) -> tuple[Path, str]:
    if arg is not None:
        return arg, f"`{arg}`"
    out = tmp / "dataset"
    if (SHARED / "dtu_scan24").is_dir():
        subprocess.run([str(ROOT / ".venv" / "bin" / "denoise-gs"), "dataset", "import", "dtu",
                        str(SHARED / "dtu_scan24"), "--out", str(out), "--views", "12", "--test", "4",
                        "--noise", "gaussian:25", "--layout", "cluster"], check=True, cwd=ROOT,
                       stdout=subprocess.DEVNULL)
        return out, "DTU scan24 from `../shared/data` (12 training views, 384x384, sigma 25/255, seed 0)"
    subprocess.run([str(ROOT / ".venv" / "bin" / "data-synth"), "render", "llff_like", "--out", str(out),
                    "--size", "384x288"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return out, "the built-in `llff_like` scene at 384x288 (`../shared/data` not found)"


def _run(code: Path, dataset: Path, task: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(code)}
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(dataset), task],
                          cwd=code, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"worker {task} in {code} failed:\n{proc.stderr[-3000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    if Path(result["code"]).resolve() != code.resolve():  # the code measured must be the version asked for
        raise SystemExit(f"worker {task} imported the project from {result['code']}, not {code}")
    return result


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", nargs=2, metavar=("DATASET", "TASK"))
    ap.add_argument("--dataset", type=Path)
    ap.add_argument("--base", default=DEFAULT_BASE)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--quality", action="store_true")
    ap.add_argument("--page", default="denoise_speed", help="the docs/bench page written (without .md)")
    ap.add_argument("--tasks", default="train,infer",
                    help="what to time, comma-separated: train, infer (both network widths), dct, grouped "
                         "(the Wiener steps)")
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(Path(args.worker[0]), args.worker[1])))
        return
    import numpy as np

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from _common import cpu_model, md_table, write_fragment

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        base = tmp / "base"
        base.mkdir()
        archive = subprocess.run(["git", "archive", "--format=tar", args.base], cwd=ROOT, check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
        dataset, what = _dataset(args.dataset, tmp)
        chosen = args.tasks.split(",")
        tasks = [t for t in (f"train:16:{args.steps}", f"train:32:{args.steps}", "infer:16", "infer:32", "dct",
                             "grouped") if t.split(":")[0] in chosen]
        times: dict[tuple[str, str], list[float]] = {}
        outputs: dict[tuple[str, str], dict] = {}
        start_load = os.getloadavg()
        for _ in range(args.repeats):
            for task in tasks:
                for label, code in (("base", base), ("this", ROOT)):
                    print(f"{label} {task}", flush=True)
                    result = _run(code, dataset, task)
                    times.setdefault((label, task), []).append(result["seconds"])
                    outputs[(label, task)] = result
        quality = {}
        if args.quality:
            for label, code in (("base", base), ("this", ROOT)):
                print(f"{label} quality", flush=True)
                quality[label] = _run(code, dataset, "quality")
        end_load = os.getloadavg()
    rows = []
    names = {f"train:16:{args.steps}": f"R2R training, width 16 (`default`), {args.steps} steps",
             f"train:32:{args.steps}": f"R2R training, width 32 (`best`), {args.steps} steps",
             "infer:16": "inference, 8 passes, 12 photos, width 16",
             "infer:32": "inference, 8 passes, 12 photos, width 32",
             "dct": "DCT Wiener step, 12 photos", "grouped": "grouped Wiener step, 12 photos"}
    steps = []
    for task in tasks:
        b, t = min(times[("base", task)]), min(times[("this", task)])
        rows.append([names[task], f"{b:.1f}", f"{t:.1f}", f"{b / t:.2f}x"])
        if task in ("dct", "grouped"):
            ob, ot = outputs[("base", task)], outputs[("this", task)]
            diff = float(np.max(np.abs(np.array(ob["out"]) - np.array(ot["out"]))))
            steps.append([names[task], f"{ob['psnr']:.3f}", f"{ot['psnr']:.3f}", f"{diff:.2g}"])
    body = [f"Photos: {what}. Machine: {cpu_model()}, {os.cpu_count()} cores. Base: commit `{args.base}`; this: the "
            "checkout. Each cell is the fastest of "
            f"{args.repeats} runs, the two versions alternating, each in its own process with torch's default "
            f"threads and the denoise stage's thread settings. Load average (1/5/15 min) at start "
            f"{start_load[0]:.2f}/{start_load[1]:.2f}/{start_load[2]:.2f}, at end "
            f"{end_load[0]:.2f}/{end_load[1]:.2f}/{end_load[2]:.2f}.", "",
            md_table(["what", "base (s)", "this (s)", "speed-up"], rows)]
    if steps:
        body += ["", "The Wiener steps (sigma 25/255, each photo's own DCT Wiener estimate as the pilot) scored "
                 "against `clean/`, and the largest difference between the two versions' first photo (of 1):", "",
                 md_table(["step", "PSNR base (dB)", "PSNR this (dB)", "largest difference"], steps)]
    if quality:
        qb, qt = quality["base"], quality["this"]
        diff = float(np.max(np.abs(np.array(qb["out"]) - np.array(qt["out"]))))
        body += ["", "The `default` network trained for 2000 steps (seed 0) by each version, the 12 photos "
                 "denoised and scored against `clean/`:", "",
                 md_table(["version", "PSNR (dB)", "SSIM"],  # run one after the other: no times compared
                          [["base", f"{qb['psnr']:.3f}", f"{qb['ssim']:.4f}"],
                           ["this", f"{qt['psnr']:.3f}", f"{qt['ssim']:.4f}"]]), "",
                 f"Largest difference between the two versions' first photo: {diff:.2g} (of 1)."]
    cmd = "OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/diag_denoise_speed.py" + (
        " --quality" if args.quality else "") + (f" --base {args.base}" if args.base != DEFAULT_BASE else "") + (
        f" --dataset {args.dataset}" if args.dataset else "") + (
        f" --page {args.page}" if args.page != "denoise_speed" else "") + (
        f" --tasks {args.tasks}" if args.tasks != "train,infer" else "")
    title = ("Denoiser speed on real-size photos (training and inference)" if args.tasks == "train,infer"
             else f"Denoiser speed on real-size photos ({', '.join(chosen)})")
    write_fragment(args.page, title, "\n".join(body), reproduce=cmd)


if __name__ == "__main__":
    main()
