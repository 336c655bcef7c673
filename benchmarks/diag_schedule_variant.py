"""`denoise-gs eval` with the `fast` preset changed: argv[1] = comma-separated variants, the rest the CLI's
arguments. Variants: "reuse_off" (PipelineConfig.reuse_noisy_splat=False), "passes=N"
(DenoiseSettings.passes), "handover" (rounds >= 2 keep the previous round's alignment whenever it holds
every selected view: `choose_geometry`'s decision forced to the handover), "no_stop"
(PipelineConfig.stop_when_unrefined=False: a round whose refine kept the previous network still aligns and
splats), "splat=NAME" (SplatSettings.preset, its own iterations), "splat_iters=N" (SplatSettings.iters),
"denoiser=METHOD" (DenoiseSettings.method, one round), "steps=N" (DenoiseSettings.n2v_steps), "fuse=0|1"
(PipelineConfig.fuse_noisy_splat), "align=NAME" (AlignSettings.preset), "photos=denoised|noisy_first"
(AlignSettings.photos), "keep_noisy=K" (DenoiseSettings.keep_noisy), "preset=NAME" (change that
preset instead of `fast`; give the same name to `--preset`).

Usage: .venv/bin/python benchmarks/diag_schedule_variant.py VARIANTS eval DATA --out OUT --preset fast ..."""
import dataclasses
import sys

import eval.cli  # first: sets the thread policy before torch loads
import eval.pipeline.align_stage as align_stage
import eval.pipeline.config as config

variants = [v for v in sys.argv[1].split(",") if v]
name = next((v.split("=", 1)[1] for v in variants if v.startswith("preset=")), "fast")
fast = config.PRESETS[name]
for v in variants:
    if v.startswith("preset="):
        continue
    if v == "reuse_off":
        fast = dataclasses.replace(fast, reuse_noisy_splat=False)
    elif v == "no_stop":
        fast = dataclasses.replace(fast, stop_when_unrefined=False)
    elif v.startswith("passes="):
        fast = dataclasses.replace(fast, denoise=dataclasses.replace(fast.denoise, passes=int(v.split("=")[1])))
    elif v.startswith("splat="):
        fast = dataclasses.replace(fast, splat=config.SplatSettings(preset=v.split("=")[1]))
    elif v.startswith("splat_iters="):
        fast = dataclasses.replace(fast, splat=dataclasses.replace(fast.splat, iters=int(v.split("=")[1])))
    elif v.startswith("denoiser="):
        fast = dataclasses.replace(fast, rounds=1,
                                   denoise=dataclasses.replace(fast.denoise, method=v.split("=")[1]))
    elif v.startswith("steps="):
        fast = dataclasses.replace(fast, denoise=dataclasses.replace(fast.denoise, n2v_steps=int(v.split("=")[1])))
    elif v.startswith("keep_noisy="):
        fast = dataclasses.replace(fast, denoise=dataclasses.replace(fast.denoise,
                                                                     keep_noisy=float(v.split("=")[1])))
    elif v.startswith("fuse="):
        fast = dataclasses.replace(fast, fuse_noisy_splat=bool(int(v.split("=")[1])))
    elif v.startswith("align="):
        fast = dataclasses.replace(fast, align=dataclasses.replace(fast.align, preset=v.split("=")[1]))
    elif v.startswith("photos="):
        fast = dataclasses.replace(fast, align=dataclasses.replace(fast.align, photos=v.split("=")[1]))
    elif v == "handover":
        real = align_stage.choose_geometry

        def forced(mode, views, previous, current, *, current_error=None, _real=real):
            ch = _real(mode, views, previous, current, current_error=current_error)
            if not ch.used_previous and ch.previous_registered == len(ch.views):
                ch = dataclasses.replace(ch, used_previous=True, reason="handover forced; rule: " + ch.reason)
            return ch

        align_stage.choose_geometry = forced
    else:
        raise SystemExit(f"unknown variant {v}")
config.PRESETS[name] = fast
print(f"{name} preset:", fast, flush=True)
raise SystemExit(eval.cli.main(sys.argv[2:]))
