"""The Denoise-GS pipeline: typed settings, resumable stages, the rounds, the report.

Public API:

- `PipelineConfig`, `PRESETS` (`fast`, `default`, `best`), `preset(name, *, views=..., ...)`;
- `run_pipeline(images_dir, out, config, *, stages=None, force=False) -> PipelineResult`;
- `StageRunner`, `StageSpec`, `StageContext`, `StageResult` (the resumable-stage machinery);
- `PipelineStages`, `product_stages()` (the stage functions; tests pass their own);
- `RoundSettings`, `round_settings(config, r)` (the typed settings each stage receives);
- `validate_run_inputs`, `validate_dataset_folder` (up-front checks).
"""

from eval.pipeline.config import PRESETS, AlignSettings, DenoiseSettings, PipelineConfig, SplatSettings, preset
from eval.pipeline.run import PipelineResult, RoundResult, run_pipeline
from eval.pipeline.stage import StageContext, StageResult, StageRunner, StageSpec
from eval.pipeline.stage_settings import RoundSettings, round_settings, stage_seed
from eval.pipeline.stages import PipelineStages, product_stages
from eval.pipeline.validate import DatasetFolder, validate_dataset_folder, validate_run_inputs

__all__ = [
    "PRESETS",
    "AlignSettings",
    "DatasetFolder",
    "DenoiseSettings",
    "PipelineConfig",
    "PipelineResult",
    "PipelineStages",
    "RoundResult",
    "RoundSettings",
    "SplatSettings",
    "StageContext",
    "StageResult",
    "StageRunner",
    "StageSpec",
    "preset",
    "product_stages",
    "round_settings",
    "run_pipeline",
    "stage_seed",
    "validate_dataset_folder",
    "validate_run_inputs",
]
