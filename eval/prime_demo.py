"""`make demo`'s first step: open `denoise-gs eval`'s output folder and put the scene's training photos in it.

The demo runs `denoise-gs run` on `EVAL/inputs/SCENE` into `EVAL/runs/SCENE/seed0/product` (to show a
pipeline report), then `denoise-gs eval DATASET --out EVAL`, which resumes in that folder and reuses the
run. The folder is opened here as `denoise-gs eval` opens it (`prepare_output` with `resume=True`: a new or
empty folder, or a previous `denoise-gs eval` output; anything else is refused), so the evaluation later
recognises it by its manifest.

Usage: python -m eval.prime_demo DATASET EVAL_OUT
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from mvgeo.common.cli import run_cli


def _prime(args: argparse.Namespace) -> int:
    from eval.evaluate import copy_train_inputs
    from eval.pipeline import validate_dataset_folder
    from mvgeo.common.output import prepare_output, resumable_output_dir

    dataset = validate_dataset_folder(Path(args.dataset))
    plan = prepare_output(args.eval_out, command="denoise-gs eval", inputs=[args.dataset], resume=True)
    with resumable_output_dir(plan) as out:
        copy_train_inputs(dataset, out / "inputs" / dataset.root.name)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m eval.prime_demo", description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="the scene's dataset folder (images/, clean/, split.json, sparse/0)")
    parser.add_argument("eval_out", help="the --out folder `denoise-gs eval` will use")
    return run_cli(_prime, parser, argv)


if __name__ == "__main__":
    sys.exit(main())
