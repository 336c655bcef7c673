"""Score every finished round of pipeline runs on their dataset's held-out views, as `denoise-gs eval` scores
the last one (`eval.evaluate.score_reconstruction`: estimated cameras registered to the ground truth,
held-out poses refined, renders against the clean images). Shows what a later round changed, or what stopping
after round 1 (`PipelineConfig.stop_when_unrefined`) gives up, on runs that exist.

Usage: .venv/bin/python benchmarks/diag_score_rounds.py RUN=DATASET [RUN=DATASET ...]
(RUN: a pipeline output folder holding round1/, round2/, ...; DATASET: the dataset folder it was built from,
at the run's working size, e.g. an evaluation's `data/<scene>`). Prints one line per round."""
import sys
from pathlib import Path

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from eval.evaluate import score_reconstruction
from eval.pipeline.validate import validate_dataset_folder

for arg in sys.argv[1:]:
    run, data = arg.split("=", 1)
    dataset = validate_dataset_folder(Path(data))
    for rd in sorted(Path(run).glob("round*")):
        if (rd / "point_cloud.ply").is_file():
            scores = score_reconstruction(rd, dataset)
            print(run, rd.name, {k: round(v, 4) for k, v in scores.items()}, flush=True)
