"""StageRunner: keys, skipping, output checks, atomic commit, and errors; config presets; component lookup."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil

import pytest

from eval.pipeline import PRESETS, MissingComponentError, StageRunner, StageSpec, preset
from eval.pipeline.components import component_config, require
from eval.pipeline.hashing import file_sha256, hash_json, tree_files
from eval.pipeline.stage import verify_outputs
from eval.pipeline.stages import _align_config
from mvgeo.common.errors import ConfigError, DgsError


def _writer(text: str, calls: list):
    def fn(ctx):
        calls.append(ctx.seed)
        (ctx.work_dir / "a.txt").write_text(text)
        (ctx.work_dir / "d").mkdir()
        (ctx.work_dir / "d" / "b.txt").write_text(text * 2)
        return {"n": len(text)}
    return fn


def _spec(tmp_path, fn, **kw):
    base = {"name": "s", "stage_dir": tmp_path / "st", "fn": fn, "outputs": ("a.txt", "d")}
    base.update(kw)
    return StageSpec(**base)


def test_key_depends_on_settings_seed_inputs_and_upstream(tmp_path):
    f = tmp_path / "in.txt"
    f.write_text("x")
    fn = _writer("a", [])
    base = _spec(tmp_path, fn, inputs={"f": f}, hashed_inputs=("f",), settings={"k": 1}, seed=3)
    k0 = base.key()
    assert _spec(tmp_path, fn, inputs={"f": f}, hashed_inputs=("f",), settings={"k": 1}, seed=3).key() == k0
    assert _spec(tmp_path, fn, inputs={"f": f}, hashed_inputs=("f",), settings={"k": 2}, seed=3).key() != k0
    assert _spec(tmp_path, fn, inputs={"f": f}, hashed_inputs=("f",), settings={"k": 1}, seed=4).key() != k0
    f.write_text("y")
    assert base.key() != k0
    up = StageRunner().run(_spec(tmp_path, fn, name="up"))
    assert _spec(tmp_path, fn, inputs={"f": f}, hashed_inputs=("f",), settings={"k": 1}, seed=3,
                 upstream=(up,)).key() != base.key()


def test_commit_skip_and_replace(tmp_path):
    calls: list = []
    runner = StageRunner()
    r1 = runner.run(_spec(tmp_path, _writer("one", calls)))
    assert not r1.skipped and r1.summary == {"n": 3}
    assert (tmp_path / "st" / "a.txt").read_text() == "one"
    assert (tmp_path / "st" / "d" / "b.txt").read_text() == "oneone"
    rec = json.loads((tmp_path / "st" / "stages" / "s.json").read_text())
    assert rec["key"] == r1.key
    r2 = runner.run(_spec(tmp_path, _writer("one", calls)))
    assert r2.skipped and r2.summary == {"n": 3} and len(calls) == 1
    # Deleting an output makes the stage incomplete.
    (tmp_path / "st" / "a.txt").unlink()
    assert not runner.run(_spec(tmp_path, _writer("one", calls))).skipped
    # New settings: outputs are replaced, folders included (no stale files inside `d`).
    (tmp_path / "st" / "d" / "stale.txt").write_text("old")
    runner.run(_spec(tmp_path, _writer("two", calls), settings={"v": 2}))
    assert (tmp_path / "st" / "a.txt").read_text() == "two"
    assert sorted(p.name for p in (tmp_path / "st" / "d").iterdir()) == ["b.txt"]
    assert list(runner.timer.seconds) == ["s"]


def test_record_holds_size_and_sha256_of_every_output_file(tmp_path):
    res = StageRunner().run(_spec(tmp_path, _writer("one", [])))
    st = tmp_path / "st"
    manifest = json.loads((st / "stages" / "s.json").read_text())["manifest"]
    assert manifest["outputs"] == {"a.txt": "file", "d": "dir"}
    # Reference: hashlib over each file's bytes.
    assert manifest["files"] == {rel: {"size": (st / rel).stat().st_size,
                                       "sha256": hashlib.sha256((st / rel).read_bytes()).hexdigest()}
                                 for rel in ("a.txt", "d/b.txt")}
    assert res.outputs_digest == hash_json(manifest)
    assert verify_outputs(st, manifest) is None


@pytest.mark.parametrize(("damage", "reason"), [
    (lambda st: (st / "a.txt").write_text("on"), "a.txt has 2 bytes, 3 recorded"),
    (lambda st: (st / "d" / "b.txt").write_text("ONEONE"), "d/b.txt changed"),  # same size
    (lambda st: (st / "d" / "b.txt").unlink(), "d/b.txt is missing"),
    (lambda st: (st / "d" / "new.txt").write_text("x"), "d/new.txt was not written by the stage"),
    (lambda st: shutil.rmtree(st / "d"), "d is missing"),
    (lambda st: (shutil.rmtree(st / "d"), (st / "d").write_text("x")), "d is not a dir"),
])
def test_damaged_output_reruns_the_stage(tmp_path, damage, reason):
    calls: list = []
    runner = StageRunner()
    first = runner.run(_spec(tmp_path, _writer("one", calls)))
    st = tmp_path / "st"
    manifest = json.loads((st / "stages" / "s.json").read_text())["manifest"]
    damage(st)
    assert reason in verify_outputs(st, manifest)
    again = runner.run(_spec(tmp_path, _writer("one", calls)))
    assert not again.skipped and len(calls) == 2
    assert again.outputs_digest == first.outputs_digest and verify_outputs(st, manifest) is None
    assert runner.run(_spec(tmp_path, _writer("one", calls))).skipped and len(calls) == 2


def test_hidden_files_in_output_folders_are_not_outputs(tmp_path):
    calls: list = []
    StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    (tmp_path / "st" / "d" / ".DS_Store").write_text("x")
    assert StageRunner().run(_spec(tmp_path, _writer("one", calls))).skipped and len(calls) == 1


def test_key_depends_on_upstream_outputs(tmp_path):
    # Same upstream key (closure values are not in it), different bytes written: downstream keys differ.
    up_a = StageRunner().run(_spec(tmp_path / "a", _writer("one", []), name="up"))
    up_b = StageRunner().run(_spec(tmp_path / "b", _writer("two", []), name="up"))
    assert up_a.key == up_b.key and up_a.outputs_digest != up_b.outputs_digest
    down = [_spec(tmp_path, _writer("x", []), upstream=(u,)).key() for u in (up_a, up_b)]
    assert down[0] != down[1]


def test_failing_stage_leaves_old_outputs_unrecorded(tmp_path):
    runner = StageRunner()
    runner.run(_spec(tmp_path, _writer("one", [])))

    def boom(ctx):
        (ctx.work_dir / "a.txt").write_text("half")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        runner.run(_spec(tmp_path, boom, settings={"v": 2}))
    assert (tmp_path / "st" / "a.txt").read_text() == "one"  # untouched
    assert not (tmp_path / "st" / "stages" / "s.json").exists()  # ...but no longer trusted
    assert not [p for p in (tmp_path / "st").iterdir() if p.name.startswith(".")]


def test_undeclared_output_and_bad_summary(tmp_path):
    def lazy(ctx):
        (ctx.work_dir / "a.txt").write_text("x")
        return {}

    with pytest.raises(DgsError, match=r"\['d'\]"):
        StageRunner().run(_spec(tmp_path, lazy))

    def bad_summary(ctx):
        _writer("x", [])(ctx)
        return {"obj": object()}

    with pytest.raises(DgsError, match="JSON"):
        StageRunner().run(_spec(tmp_path, bad_summary))
    assert not (tmp_path / "st" / "stages" / "s.json").exists()


def test_presets_and_validation():
    assert set(PRESETS) == {"fast", "default", "best"}
    assert preset("fast", views=4, rounds=3).views == 4
    assert preset("default") == PRESETS["default"]
    with pytest.raises(ConfigError, match="preset"):
        preset("fastest")
    with pytest.raises(ConfigError, match="views"):
        preset("fast", views=1)
    with pytest.raises(ConfigError, match="rounds"):
        preset("fast", rounds=0)
    with pytest.raises(ConfigError, match="align.points"):
        dataclasses.replace(PRESETS["fast"], align=dataclasses.replace(PRESETS["fast"].align, points=0))


def test_align_settings_reach_the_align_config():
    """The pipeline's align settings (preset + overrides) become the AlignConfig the stage runs."""
    from mvgeo.align import PREVIEW, AlignConfig

    fast = dataclasses.asdict(PRESETS["fast"].align)
    cfg = _align_config(fast, seed=3, need="test")
    assert cfg.points_budget == PRESETS["fast"].align.points != PREVIEW.points_budget
    assert cfg.max_size_px == PREVIEW.max_size_px and cfg.seed == 3
    default = _align_config(dataclasses.asdict(PRESETS["default"].align), seed=0, need="test")
    assert default.points_budget == AlignConfig().points_budget  # None keeps the preset's
    over = _align_config({**fast, "points": 1234, "iters": 7, "max_size_px": 99}, seed=0, need="test")
    assert (over.points_budget, over.align.iters, over.max_size_px) == (1234, 7, 99)


def test_missing_components_are_named():
    with pytest.raises(MissingComponentError, match="no_such_pkg_xyz"):
        require("no_such_pkg_xyz", "f", needed_for="test")
    with pytest.raises(MissingComponentError, match="eval.psnr.train_everything"):
        require("eval.psnr", "train_everything", needed_for="test")
    with pytest.raises(MissingComponentError, match="PRESETS_NOPE"):
        component_config("eval.pipeline.config", "PRESETS_NOPE", "fast", {}, needed_for="test")
    # A real presets table: unknown preset and unknown field are named too.
    with pytest.raises(MissingComponentError, match="'turbo'"):
        component_config("eval.pipeline.config", "PRESETS", "turbo", {}, needed_for="test")
    with pytest.raises(MissingComponentError, match="steps"):
        component_config("eval.pipeline.config", "PRESETS", "fast", {"steps": 3}, needed_for="test")
    cfg = component_config("eval.pipeline.config", "PRESETS", "fast", {"views": 5, "rounds": None},
                           needed_for="test")
    assert cfg.views == 5 and cfg.rounds == PRESETS["fast"].rounds


def test_file_hashes_against_hashlib(tmp_path):
    big = tmp_path / "big.bin"
    big.write_bytes(bytes(range(256)) * 9000)  # over one read chunk
    assert file_sha256(big) == hashlib.sha256(big.read_bytes()).hexdigest()
    (tmp_path / "sub" / ".hidden").mkdir(parents=True)
    for rel in ("sub/z.txt", "sub/.hidden/h.txt", ".top.txt", "a.txt"):
        (tmp_path / rel).write_text(rel)
    assert [p.relative_to(tmp_path).as_posix() for p in tree_files(tmp_path)] == ["a.txt", "big.bin", "sub/z.txt"]
