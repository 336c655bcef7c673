"""A user's file named like a stage record is refused with `UnownedOutputError` (exit 2), whatever
it holds, never a crash, and nothing is replaced."""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path

import pytest

from eval.pipeline import StageRunner, StageSpec
from eval.pipeline.stage import UnownedOutputError, adopt_outputs, check_outputs_owned, commit_written


def _fn(ctx):
    (ctx.work_dir / "a.txt").write_text("new")
    return {}


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_users_deeply_nested_json_file_named_like_the_record_is_refused_not_a_crash(tmp_path):
    st = tmp_path / "st"
    (st / "stages").mkdir(parents=True)
    record = st / "stages" / "s.json"
    record.write_text("[" * 100_000 + "]" * 100_000)
    before = _sha(record)
    with pytest.raises(UnownedOutputError, match="s.json"):
        StageRunner().run(StageSpec(name="s", stage_dir=st, fn=_fn, outputs=("a.txt",)))
    with pytest.raises(UnownedOutputError, match="s.json"):
        check_outputs_owned(st, "s", ["a.txt"])
    with pytest.raises(UnownedOutputError, match="s.json"):
        commit_written(st, "s", ["a.txt"], lambda work: (work / "a.txt").write_text("x"))
    with pytest.raises(UnownedOutputError, match="s.json"):
        adopt_outputs(st, "s", ["a.txt"])
    assert _sha(record) == before and sorted(p.name for p in st.iterdir()) == ["stages"]


def test_linking_round1_never_removes_a_users_folder_named_like_its_temporary_one(tmp_path):
    from eval.methods import share_round1

    src, dst = tmp_path / "src", tmp_path / "dst"
    (src / "round1" / "stages").mkdir(parents=True)
    (src / "round1" / "stages" / "denoise.json").write_text("{}")
    mine = dst / ".round1.link-tmp"
    mine.mkdir(parents=True)
    (mine / "notes.txt").write_text("mine")
    assert share_round1(src, dst)
    assert (mine / "notes.txt").read_text() == "mine"
    assert (dst / "round1" / "stages" / "denoise.json").read_text() == "{}"
    assert sorted(p.name for p in dst.iterdir() if p.name.startswith(".round1")) == [".round1.link-tmp"]


KILLED_WHILE_LINKING = """
import os, signal, sys
from eval.methods import share_round1
calls = []
real_link = os.link

def link(a, b):
    if calls:
        os.kill(os.getpid(), signal.SIGKILL)  # a worker killed while it links round 1
    calls.append(a)
    real_link(a, b)

os.link = link
share_round1(sys.argv[1], sys.argv[2])
"""


def test_a_round1_link_cut_short_by_a_kill_is_a_leftover_the_next_run_removes(tmp_path):
    """A worker killed while `share_round1` linked round 1 left its temporary folder in the ablation's run folder,
    which then held a file `denoise-gs run` did not write: the resumed evaluation was refused."""
    import subprocess
    import sys

    from eval.methods import share_round1
    from eval.pipeline.run import RUN_COMMAND
    from mvgeo.common.output import prepare_output

    src, dst = tmp_path / "src", tmp_path / "dst"
    (src / "round1" / "stages").mkdir(parents=True)
    (src / "round1" / "stages" / "denoise.json").write_text("{}")
    (src / "round1" / "n2v_model.pt").write_text("net")
    repo = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-c", KILLED_WHILE_LINKING, str(src), str(dst)], cwd=repo,
                          env={**os.environ, "PYTHONPATH": str(repo)}, capture_output=True, text=True, timeout=120)
    assert done.returncode == -9, done.stderr[-2000:]
    assert not (dst / "round1").exists() and any(dst.iterdir())  # the kill came mid-copy
    prepare_output(dst, command=RUN_COMMAND, resume=True)  # not refused
    assert share_round1(src, dst)
    assert sorted(p.name for p in dst.iterdir()) == [".denoise-gs-output.json", "round1"]
    assert (dst / "round1" / "n2v_model.pt").read_text() == "net"


def test_a_pending_record_naming_other_paths_as_retired_removes_nothing_else(tmp_path):
    """Only `.<output>.old-<8 hex>` of the stage's own outputs are ever removed as retired outputs."""
    import json

    from eval.pipeline.stage import StageRunner, StageSpec

    def fn(ctx):
        (ctx.work_dir / "a.txt").write_text("a")
        return {}

    st = tmp_path / "st"
    StageRunner().run(StageSpec(name="s", stage_dir=st, fn=fn, outputs=("a.txt",)))
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "f.txt").write_text("mine")
    (st / ".b.txt.old-zzzzzzzz").mkdir()
    record = st / "stages" / "s.json"
    rec = json.loads(record.read_text())
    rec.update(pending=True, retired={"../precious": "../precious", "b.txt": ".b.txt.old-zzzzzzzz"})
    record.write_text(json.dumps(rec))
    StageRunner().run(StageSpec(name="s", stage_dir=st, fn=fn, outputs=("a.txt",), settings={"v": 2}))
    assert (tmp_path / "precious" / "f.txt").read_text() == "mine" and (st / ".b.txt.old-zzzzzzzz").is_dir()


NESTED = "[" * 100_000 + "]" * 100_000


def test_the_toolkits_own_json_files_deeply_nested_give_typed_errors_or_not_ours(tmp_path):
    """`sizes.json`, a working dataset's record, a cost point's score cache and a denoise stage record, each
    replaced by deeply nested JSON: a typed error naming the file, "not ours", or the original refusal; never
    a RecursionError traceback."""
    from eval.cost import _cached_scores
    from eval.methods import METHODS, _denoised_before_refusal
    from eval.pipeline import preset
    from eval.pipeline.inputs import _recorded_dataset, read_sizes, working_focal_prior
    from eval.pipeline.stage import RECORD_DIR
    from mvgeo.common.errors import DisconnectedViewsError, InputError

    sizes = tmp_path / "inputs" / "sizes.json"
    sizes.parent.mkdir()
    sizes.write_text(NESTED)
    with pytest.raises(InputError, match="nested too deeply") as exc:
        read_sizes(sizes)
    assert "sizes.json" in str(exc.value)
    with pytest.raises(InputError, match="nested too deeply"):
        working_focal_prior(sizes.parent)
    sizes.write_text("[1, 2]")  # not an object
    with pytest.raises(InputError, match="cannot read the working sizes"):
        read_sizes(sizes)

    (tmp_path / "data" / RECORD_DIR).mkdir(parents=True)
    (tmp_path / "data" / RECORD_DIR / "scene.json").write_text(NESTED)
    assert _recorded_dataset(tmp_path / "data", "scene", tmp_path / "src", 512, "0" * 64) is False

    cache = tmp_path / "scores.json"
    cache.write_text(NESTED)
    with pytest.raises(InputError, match="cached scores") as exc:
        _cached_scores(cache, {"k": 1})
    assert "scores.json" in str(exc.value)

    (tmp_path / "m" / "round1" / "stages").mkdir(parents=True)
    (tmp_path / "m" / "round1" / "stages" / "denoise.json").write_text(NESTED)
    refusal = DisconnectedViewsError("the pair graph is disconnected")
    with pytest.raises(DisconnectedViewsError) as exc:
        _denoised_before_refusal(METHODS["product"], preset("default"), tmp_path / "m", refusal)
    assert exc.value is refusal


def test_completed_seconds_reads_only_a_completed_record(tmp_path):
    """`completed_seconds`: a record a finished commit wrote gives its seconds; a pending one (a commit cut
    short), none, one without a number, or one that is not JSON give None. `_denoised_before_refusal`
    splats round 1's photos only on the first."""
    from eval.methods import METHODS, _denoised_before_refusal
    from eval.pipeline import preset
    from eval.pipeline.stage import RECORD_DIR, completed_seconds
    from mvgeo.common.errors import DisconnectedViewsError

    rd = tmp_path / "m" / "round1"
    (rd / RECORD_DIR).mkdir(parents=True)
    record = rd / RECORD_DIR / "denoise.json"
    assert completed_seconds(rd, "denoise") is None
    cfg = dataclasses.replace(preset("default"), fuse_noisy_splat=False)
    refusal = DisconnectedViewsError("the pair graph is disconnected")
    for text in ('{"name": "denoise", "pending": true, "seconds": 3.0}', '{"seconds": "3"}', '{"seconds": true}',
                 "[1]", "not json"):
        record.write_text(text)
        assert completed_seconds(rd, "denoise") is None, text
        with pytest.raises(DisconnectedViewsError):
            _denoised_before_refusal(METHODS["product"], cfg, tmp_path / "m", refusal)
    record.write_text('{"name": "denoise", "seconds": 12.5}')
    assert completed_seconds(rd, "denoise") == 12.5
    rec = _denoised_before_refusal(METHODS["product"], cfg, tmp_path / "m", refusal)
    assert rec.round_dir == rd and rec.seconds == 12.5
