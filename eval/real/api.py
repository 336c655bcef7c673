"""`import_dataset`: a real capture (LLFF, COLMAP, Middlebury, DTU) -> the project's dataset layout."""

from __future__ import annotations

from pathlib import Path

from eval.real.capture import Capture
from eval.real.colmap_model import read_colmap
from eval.real.degrade import Degradation, parse_noise
from eval.real.dtu import read_dtu
from eval.real.layout import ImportConfig, write_capture
from eval.real.llff import read_llff
from eval.real.middlebury import read_middlebury
from mvgeo.common.errors import InputError
from mvgeo.common.output import OutputPlan

__all__ = ["KINDS", "import_dataset", "read_capture"]

#: The capture formats `import_dataset` reads.
KINDS = ("llff", "colmap", "middlebury", "dtu")


def read_capture(kind: str, src: str | Path, *, llff_factor: int | None = None) -> Capture:
    """Read a capture of format `kind` (one of `KINDS`) into views with cameras in our conventions.

    Args:
        kind: "llff" (`poses_bounds.npy` + `images[_N]/`), "colmap" (`sparse/0` + `images/`),
            "middlebury" (`*_par.txt` or its folder), "dtu" (`cameras.npz` + `images/`).
        src: the capture folder (or the `*_par.txt` file).
        llff_factor: LLFF only: read `images_<factor>/`.

    Raises:
        InputError: unknown kind, or the reader's input errors.
    """
    if llff_factor is not None and kind != "llff":
        raise InputError(f"--factor applies to LLFF captures only, not {kind}",
                         fix="leave --factor out (--size or --max-size scales any capture)")
    if kind == "llff":
        return read_llff(src, factor=llff_factor)
    if kind == "colmap":
        return read_colmap(src)
    if kind == "middlebury":
        return read_middlebury(src)
    if kind == "dtu":
        return read_dtu(src)
    raise InputError(f"unknown capture format {kind!r}", fix=f"use one of {', '.join(KINDS)}")


def import_dataset(kind: str, src: str | Path, out: str | Path | OutputPlan, *, views: int | None = None,
                   test_every: int | None = None, test: int | None = None,
                   noise: str | Degradation | None = None, seed: int = 0, layout: str = "spread",
                   size_wh: tuple[int, int] | None = None, max_size_px: int | None = None,
                   llff_factor: int | None = None, overwrite: bool = False) -> Path:
    """Import a real capture as a dataset folder (`images/`, `clean/`, `split.json`, `sparse/0/`, `meta.json`).

    Args:
        kind, src, llff_factor: see `read_capture`.
        out: the dataset folder to write (atomically), or a plan from `eval.real.layout.output_plan`. A
            new or empty folder, or a previous import with `overwrite`; anything else is refused
            (`mvgeo.common.output`).
        views: training views, spread over the candidates (None: all non-held-out views; 12 for
            `layout="cluster"`).
        test_every: hold out views 0, K, 2K, ... (LLFF's convention; the default, K = 8, when neither
            this nor `test` is given).
        test: hold out this many views instead (midway between training views, or inside them for the
            cluster layout; default 4 there).
        noise: a `--noise` spec ("gaussian:25", "poisson-gaussian:0.01,5", None/"none") or a parsed
            `Degradation`; exactly this is added to `images/`, nothing else.
        seed: noise seed (per view: `default_rng([seed, crc32(view name), 0])`).
        layout: "spread" or "cluster" (see `eval.real.layout.ImportConfig`).
        size_wh: output (width, height); intrinsics scaled exactly.
        max_size_px: downscale so that the longer side is at most this.
        overwrite: replace an earlier import at `out`.

    Returns:
        The dataset folder (absolute).

    Raises:
        InputError: bad options or input files (named, with a fix), before anything is written.
    """
    degradation = noise if isinstance(noise, Degradation) else parse_noise(noise)
    config = ImportConfig(views=views, test_every=test_every, test=test, layout=layout,
                          size_wh=None if size_wh is None else (int(size_wh[0]), int(size_wh[1])),
                          max_size_px=max_size_px, noise=degradation, seed=int(seed), overwrite=overwrite)
    capture = read_capture(kind, src, llff_factor=llff_factor)
    return write_capture(capture, out, config)
