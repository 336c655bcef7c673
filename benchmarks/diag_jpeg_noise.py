"""What a JPEG round trip does to the noise levels the denoisers read: colour patches against luma.

For each imported dataset folder (`denoise-gs dataset import ... --noise ...`), its training photos as they are
and after a JPEG round trip at each quality (OpenCV's encoder, 4:2:0 chroma, as `--noise ...+jpeg:Q` writes
them): the PCA noise level of the colour patches on the photos and on their stride-2 sub-images
(`denoise.pixel_shuffle`), the level the luma reads (`denoise.noise_level.luma_noise_sigma`, RGB-equivalent)
on both, the spread of the luma's patch eigenvalues (`denoise.noise_level.luma_noise_spread`: about 1 for white
noise), and what `denoise.pixel_shuffle.choose_stride` decides from them. Levels /255, the median over six photos
spread over the training views; with `--clean`, the folder's `clean/` photos too.

With `--per-photo`, instead: for each dataset's 12 training photos as they are, at the stride `choose_stride`
gives them, on how many photos (or sub-images) the denoisers read the level on the luma
(`denoise.noise_level.chroma_subsampled_noise_sigma`'s rule), and the range of colour / luma and of the luma's level.

Usage: .venv/bin/python benchmarks/diag_jpeg_noise.py DATASET [DATASET ...] [--qualities 95 90 80] [--clean]
       .venv/bin/python benchmarks/diag_jpeg_noise.py DATASET [DATASET ...] --per-photo
"""
import argparse
import json
from pathlib import Path

import numpy as np

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from data_synth.effects import EffectContext, apply_effects, parse_effect
from denoise.noise_level import (
    chroma_subsampled_sigma,
    estimate_noise_sigma_pca,
    luma_noise_sigma,
    luma_noise_spread,
)
from denoise.pixel_shuffle import MAX_PHOTOS, choose_stride, pd_split, shuffled
from mvgeo.common.imageio import read_image


def jpeg_round_trip(img: np.ndarray, quality: int) -> np.ndarray:
    """`img` ((H, W, 3) in [0, 1]) through an 8-bit JPEG at `quality`: `data_synth`'s `jpeg` effect, as the
    import's `+jpeg:Q` step applies it."""
    effect = parse_effect({"type": "jpeg", "quality": int(quality)}, key="--qualities", path=None)
    return apply_effects(img, (effect,), seed=0, ctx=EffectContext("diag", np.eye(3)))


def level_255(images: list[np.ndarray], stride: int, luma: bool) -> float:
    read = luma_noise_sigma if luma else estimate_noise_sigma_pca
    return 255.0 * float(np.median([np.median([read(p) for p in pd_split(im, stride)]) for im in images]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", type=Path, nargs="+")
    ap.add_argument("--qualities", type=int, nargs="+", default=[95, 90, 80])
    ap.add_argument("--clean", action="store_true", help="the clean photos too")
    ap.add_argument("--per-photo", action="store_true", help="where the luma rule fires, photo by photo")
    args = ap.parse_args()
    if args.per_photo:
        return per_photo(args.datasets)
    print("| photos | JPEG quality | colour, photos | colour, stride 2 | luma, photos | colour / luma | "
          "luma eigenvalue spread | luma, stride 2 | colour / luma, stride 2 | choose_stride |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for d in args.datasets:
        names = json.loads((d / "split.json").read_text())["train"]
        pick = [names[int(i)] for i in np.linspace(0, len(names) - 1, min(MAX_PHOTOS, len(names)))]
        for sub in (["clean"] if args.clean else []) + ["images"]:
            base = [read_image(d / sub / n) for n in pick]
            for q in [None, *args.qualities]:
                ims = base if q is None else [jpeg_round_trip(im, q) for im in base]
                c1, c2, y1 = level_255(ims, 1, False), level_255(ims, 2, False), level_255(ims, 1, True)
                y2 = level_255(ims, 2, True)
                spread = float(np.median([luma_noise_spread(im) for im in ims]))
                read = choose_stride(ims)
                how = f"stride {read.stride}" + ("" if read.luma_level is None else
                                                 f", luma {255.0 * read.luma_level:.1f}")
                how += "" if read.luma_hint_level is None else f" (hint: luma {255.0 * read.luma_hint_level:.1f})"
                print(f"| {d.name} {sub}/ | {q or 'none'} | {c1:.2f} | {c2:.2f} | {y1:.2f} | {c1 / max(y1, 1e-9):.2f} "
                      f"| {spread:.2f} | {y2:.2f} | {c2 / max(y2, 1e-9):.2f} | {how} |", flush=True)
    return 0


def per_photo(datasets: list[Path]) -> int:
    print("| photos | stride | level read on the luma | colour / luma | luma (/255) |")
    print("|---|---|---|---|---|")
    for d in datasets:
        ims = [read_image(d / "images" / n) for n in json.loads((d / "split.json").read_text())["train"]]
        stride = choose_stride(ims).stride
        work = ims if stride == 1 else shuffled(ims, stride)
        # The readings `chroma_subsampled_noise_sigma` makes, each once.
        luma = np.array([luma_noise_sigma(w, exclude_clipped=True) for w in work])
        colour = np.array([estimate_noise_sigma_pca(w, exclude_clipped=True) for w in work])
        fired = sum(chroma_subsampled_sigma(c, y) is not None for c, y in zip(colour, luma, strict=True))
        ratio = colour / np.maximum(luma, 1e-9)
        print(f"| {d.name} | {stride} | {fired} of {len(work)} | {ratio.min():.2f}-{ratio.max():.2f} | "
              f"{255 * luma.min():.1f}-{255 * luma.max():.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
