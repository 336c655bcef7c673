"""`denoise-gs eval` with the `fast` preset changed: argv[1] = comma-separated variants, the rest the CLI's
arguments. Variants: "reuse_off" (PipelineConfig.reuse_noisy_splat=False), "passes=N"
(DenoiseSettings.passes), "handover" (rounds >= 2 keep the previous round's alignment whenever it holds
every selected view: `choose_geometry`'s decision forced to the handover), "no_stop"
(PipelineConfig.stop_when_unrefined=False: a round whose refine kept the previous network still aligns and
splats), "preset=NAME" (change that
preset instead of `fast`; give the same name to `--preset`).

Usage: .venv/bin/python benchmarks/diag_schedule_variant.py VARIANTS eval DATA --out OUT --preset fast ..."""
import dataclasses
import sys

import eval.cli  # first: sets the thread policy before torch loads
import eval.pipeline.config as config
import eval.pipeline.stages as stages

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
    elif v == "handover":
        real = stages.choose_geometry

        def forced(mode, views, previous, current, *, current_error=None, _real=real):
            ch = _real(mode, views, previous, current, current_error=current_error)
            if not ch.used_previous and ch.previous_registered == len(ch.views):
                ch = dataclasses.replace(ch, used_previous=True, reason="handover forced; rule: " + ch.reason)
            return ch

        stages.choose_geometry = forced
    else:
        raise SystemExit(f"unknown variant {v}")
config.PRESETS[name] = fast
print(f"{name} preset:", fast, flush=True)
raise SystemExit(eval.cli.main(sys.argv[2:]))
