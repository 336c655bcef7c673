"""`denoise.training_restart.TrainingRestart`: the divergence guard's record of an abandoned run."""

from __future__ import annotations

import json

import pytest

from denoise.training_restart import TrainingRestart


def test_a_restart_reads_back_the_json_it_writes():
    restart = TrainingRestart(step=37, lr=0.003)
    text = json.dumps(restart.to_json())
    assert text == '{"step": 37, "lr": 0.003}'  # the stage summaries' `training_restarts` entries
    assert TrainingRestart.from_json(json.loads(text)) == restart


def test_a_record_without_its_step_is_refused():
    with pytest.raises(KeyError):
        TrainingRestart.from_json({"lr": 0.003})
