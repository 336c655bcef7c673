"""Whether round 1's denoise stage passes each set's photos through undenoised, and the levels that decide it.

The stage (`eval.pipeline.stages.denoise`) reads the noise level of every photo, or of every pixel-shuffled
sub-image where the noise is correlated between neighbouring pixels, and passes the photos through when every
level is under `DenoiseSettings.pass_clean_below_255` and nothing hints at noise the level misses
(`NoiseLevels.hint`: a camera's JPEG). This reads the levels the same way, without training anything.

Usage: .venv/bin/python benchmarks/diag_pass_through.py [--below=1.5] FOLDER [FOLDER ...]
(FOLDER: a folder of photos, e.g. a dataset's `images/`). Prints a Markdown table.
"""
import sys
from pathlib import Path

from _common import cli_option

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads


def main() -> int:
    from denoise.pixel_shuffle import shuffled, stride_for
    from denoise.self_supervised import r2r_noise_std
    from eval.pipeline.quality import noise_level_255
    from eval.pipeline.stages import _reads_clean
    from eval.pipeline.views import read_views

    below = float(cli_option("below", "1.5"))
    folders = [a for a in sys.argv[1:] if not a.startswith("--")]
    if not folders:
        print(__doc__.strip().splitlines()[-2], file=sys.stderr)
        return 2
    print("| folder | stride | highest level (/255) | JPEG hint | round 1 |")
    print("|---|---|---|---|---|")
    for folder in folders:
        photos = list(read_views(Path(folder)).values())
        levels = stride_for(photos, 0, hint=True)
        read = shuffled(photos, levels.stride) if levels.stride > 1 else photos
        stds = [r2r_noise_std(im, noise_model=levels.noise_model) for im in read]
        passed = _reads_clean(stds, below) and levels.hint() is None
        print(f"| {folder} | {levels.stride} | {max(noise_level_255(v) for v in stds):.2f} | "
              f"{'yes' if levels.hint() is not None else 'no'} | {'passed through' if passed else 'denoised'} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
