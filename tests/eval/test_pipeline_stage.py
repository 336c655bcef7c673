"""StageRunner: keys, skipping, output checks, atomic commit, and errors; config presets; typed stage settings."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import shutil
from pathlib import Path

import pytest

from eval.pipeline import PRESETS, StageRunner, StageSpec, preset
from eval.pipeline.config import AlignSettings, DenoiseSettings, SplatSettings
from eval.pipeline.hashing import file_sha256, hash_json, tree_files
from eval.pipeline.stage import (
    UnownedOutputError,
    check_outputs_owned,
    settings_json,
    verify_outputs,
    withdraw_outputs,
)
from eval.pipeline.stage_settings import align_config, check_settings, round2_config, round_settings, train_config
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
    # New settings: outputs are replaced, folders included.
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


def _tree(st):
    return {p.relative_to(st).as_posix(): p.read_bytes() for p in sorted(st.rglob("*")) if p.is_file()}


@pytest.mark.parametrize(("damage", "reason"), [
    (lambda st: (st / "d" / "b.txt").unlink(), "d/b.txt is missing"),
    (lambda st: shutil.rmtree(st / "d"), "d is missing"),
])
def test_missing_output_reruns_the_stage(tmp_path, damage, reason):
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


@pytest.mark.parametrize(("damage", "reason", "culprit", "why"), [
    (lambda st: (st / "a.txt").write_text("on"), "a.txt has 2 bytes, 3 recorded", "a.txt", "changed"),
    (lambda st: (st / "d" / "b.txt").write_text("ONEONE"), "d/b.txt changed", "d/b.txt", "changed"),  # same size
    (lambda st: (st / "d" / "new.txt").write_text("x"), "d/new.txt was not written by the stage", "d/new.txt",
     "not written"),
    (lambda st: (shutil.rmtree(st / "d"), (st / "d").write_text("x")), "d is not a dir", "d", "not written"),
    (lambda st: (st / "d" / "link").symlink_to(st / "a.txt"), "d/link was not written", "d/link", "not written"),
])
@pytest.mark.parametrize("force", [False, True])
def test_changed_or_added_output_files_stop_the_stage_before_it_runs(tmp_path, damage, reason, culprit, why, force):
    """A file in a stage's outputs that the stage did not write, or whose content changed, may be the user's:
    the stage refuses to run (it would delete it), with a typed error naming the file, and changes nothing;
    once the file is moved out of the folder the stage runs again."""
    calls: list = []
    first = StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    st = tmp_path / "st"
    manifest = json.loads((st / "stages" / "s.json").read_text())["manifest"]
    damage(st)
    assert reason in verify_outputs(st, manifest)
    before = _tree(st)
    with pytest.raises(UnownedOutputError, match=re.escape(f"{st / culprit} ({why}")) as info:
        StageRunner(force=force).run(_spec(tmp_path, _writer("one", calls)))
    assert "move these files out" in info.value.fix and info.value.path == st
    assert len(calls) == 1 and _tree(st) == before
    # New settings (a stage that must run anyway): refused too.
    with pytest.raises(UnownedOutputError):
        StageRunner().run(_spec(tmp_path, _writer("one", calls), settings={"v": 2}))
    assert len(calls) == 1 and _tree(st) == before
    # The user moves the file out: an added file was the only difference, a missing output is written again.
    (st / culprit).rename(tmp_path / "kept")
    again = StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    assert again.skipped == (culprit not in manifest["files"] and culprit not in manifest["outputs"])
    assert again.outputs_digest == first.outputs_digest and verify_outputs(st, manifest) is None
    assert len(calls) == 1 + (not again.skipped)


def test_interrupted_commit_leaves_files_the_next_run_owns(tmp_path, monkeypatch):
    """A crash while outputs are being replaced leaves a pending record that owns the old and the new files:
    the next run is not refused by its own files and writes the outputs again."""
    import eval.pipeline.stage as stage_mod

    calls: list = []
    StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    real_replace, moved = stage_mod._replace, []

    def crash_after_first(src, dst, old):
        if moved:
            raise KeyboardInterrupt("killed while committing")
        moved.append(dst)
        real_replace(src, dst, old)

    monkeypatch.setattr(stage_mod, "_replace", crash_after_first)
    with pytest.raises(KeyboardInterrupt):
        StageRunner().run(_spec(tmp_path, _writer("two", calls), settings={"v": 2}))
    st = tmp_path / "st"
    assert (st / "a.txt").read_text() == "two" and (st / "d" / "b.txt").read_text() == "oneone"  # half replaced
    assert json.loads((st / "stages" / "s.json").read_text())["pending"] is True
    monkeypatch.setattr(stage_mod, "_replace", real_replace)
    res = StageRunner().run(_spec(tmp_path, _writer("two", calls), settings={"v": 2}))
    assert not res.skipped and (st / "d" / "b.txt").read_text() == "twotwo"
    assert StageRunner().run(_spec(tmp_path, _writer("two", calls), settings={"v": 2})).skipped


def _killed_before_removing_the_old_outputs(tmp_path, monkeypatch) -> Path:
    """Commit "one", then kill the commit of "two" after its outputs were renamed to their hidden retired
    names and before they were removed; returns the stage folder."""
    import eval.pipeline.stage as stage_mod

    calls: list = []
    StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    real_remove = stage_mod._remove

    def killed(path):
        if ".old-" in path.name:
            raise KeyboardInterrupt("killed while committing")
        real_remove(path)

    with monkeypatch.context() as m:
        m.setattr(stage_mod, "_remove", killed)
        with pytest.raises(KeyboardInterrupt):
            StageRunner().run(_spec(tmp_path, _writer("two", calls), settings={"v": 2}))
    return tmp_path / "st"


def test_old_outputs_a_killed_commit_moved_aside_are_removed_by_the_next_commit(tmp_path, monkeypatch):
    """The pending record names them, and the next commit removes them (only files it owns, unchanged)."""
    st = _killed_before_removing_the_old_outputs(tmp_path, monkeypatch)
    left = sorted(p.name for p in st.iterdir() if ".old-" in p.name)
    assert len(left) == 2 and left[0].startswith(".a.txt.old-") and left[1].startswith(".d.old-")
    StageRunner().run(_spec(tmp_path, _writer("three", []), settings={"v": 3}))
    assert not [p for p in st.iterdir() if ".old-" in p.name]
    assert (st / "a.txt").read_text() == "three"


def test_a_changed_old_output_left_by_a_killed_commit_is_kept(tmp_path, monkeypatch):
    st = _killed_before_removing_the_old_outputs(tmp_path, monkeypatch)
    (old,) = [p for p in st.iterdir() if p.name.startswith(".a.txt.old-")]
    old.write_text("edited by the user")
    StageRunner().run(_spec(tmp_path, _writer("three", []), settings={"v": 3}))
    assert old.read_text() == "edited by the user"


def test_a_file_added_to_an_output_during_its_commit_is_kept(tmp_path, monkeypatch):
    """A file put into a committed output after the ownership check and before the output is moved aside
    is not removed with the old output: it stays under the hidden retired name."""
    import eval.pipeline.stage as stage_mod

    calls: list = []
    StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    real_replace = stage_mod._replace

    def user_writes_first(src, dst, old):
        if dst.name == "d":
            (dst / "mine.txt").write_text("the user's")
        real_replace(src, dst, old)

    monkeypatch.setattr(stage_mod, "_replace", user_writes_first)
    StageRunner().run(_spec(tmp_path, _writer("two", calls), settings={"v": 2}))
    st = tmp_path / "st"
    (kept,) = [p for p in st.iterdir() if p.name.startswith(".d.old-")]
    assert (kept / "mine.txt").read_text() == "the user's"
    assert not [p for p in st.iterdir() if p.name.startswith(".a.txt.old-")]  # the stage's own: removed
    assert (st / "d" / "b.txt").read_text() == "twotwo"


@pytest.mark.parametrize("content", ["my notes, not JSON", '{"name": "other"}', "[1, 2]"])
def test_a_users_file_named_like_the_record_is_not_replaced(tmp_path, content):
    calls: list = []
    StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    record = tmp_path / "st" / "stages" / "s.json"
    record.write_text(content)
    with pytest.raises(UnownedOutputError, match="s.json"):
        StageRunner().run(_spec(tmp_path, _writer("two", calls), settings={"v": 2}))
    assert record.read_text() == content and (tmp_path / "st" / "a.txt").read_text() == "one"
    with pytest.raises(UnownedOutputError, match="s.json"):
        check_outputs_owned(tmp_path / "st", "s", ["a.txt"])
    with pytest.raises(UnownedOutputError, match="s.json"):
        withdraw_outputs(tmp_path / "st", "s", ["a.txt"])
    assert record.read_text() == content and (tmp_path / "st" / "a.txt").read_text() == "one"


def test_a_users_file_named_like_the_record_folder_is_refused(tmp_path):
    calls: list = []
    (tmp_path / "st").mkdir()
    (tmp_path / "st" / "stages").write_text("mine")
    with pytest.raises(UnownedOutputError, match="stages"):
        StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    assert (tmp_path / "st" / "stages").read_text() == "mine" and not calls


def test_outputs_without_a_record_are_not_replaced(tmp_path):
    calls: list = []
    StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    (tmp_path / "st" / "stages" / "s.json").unlink()
    with pytest.raises(UnownedOutputError, match="a.txt"):
        StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    assert (tmp_path / "st" / "a.txt").read_text() == "one" and len(calls) == 1


def test_hidden_files_in_output_folders_are_not_outputs(tmp_path):
    calls: list = []
    StageRunner().run(_spec(tmp_path, _writer("one", calls)))
    (tmp_path / "st" / "d" / ".DS_Store").write_text("x")
    assert StageRunner().run(_spec(tmp_path, _writer("one", calls))).skipped and len(calls) == 1
    # ...but they are not the stage's either: replacing the folder would delete them.
    with pytest.raises(UnownedOutputError, match="DS_Store"):
        StageRunner().run(_spec(tmp_path, _writer("one", calls), settings={"v": 2}))
    assert (tmp_path / "st" / "d" / ".DS_Store").read_text() == "x"


def test_key_depends_on_upstream_outputs(tmp_path):
    # Same upstream key (closure values are not in it), different bytes written: downstream keys differ.
    up_a = StageRunner().run(_spec(tmp_path / "a", _writer("one", []), name="up"))
    up_b = StageRunner().run(_spec(tmp_path / "b", _writer("two", []), name="up"))
    assert up_a.key == up_b.key and up_a.outputs_digest != up_b.outputs_digest
    down = [_spec(tmp_path, _writer("x", []), upstream=(u,)).key() for u in (up_a, up_b)]
    assert down[0] != down[1]


def test_failing_stage_leaves_old_outputs_and_their_record(tmp_path):
    runner = StageRunner()
    first = runner.run(_spec(tmp_path, _writer("one", [])))

    def boom(ctx):
        (ctx.work_dir / "a.txt").write_text("half")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        runner.run(_spec(tmp_path, boom, settings={"v": 2}))
    assert (tmp_path / "st" / "a.txt").read_text() == "one"  # untouched, and so is their record: the old key's
    assert json.loads((tmp_path / "st" / "stages" / "s.json").read_text())["key"] == first.key
    assert not [p for p in (tmp_path / "st").iterdir() if p.name.startswith(".")]
    assert not runner.run(_spec(tmp_path, _writer("two", []), settings={"v": 2})).skipped


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


def test_an_optional_output_may_be_left_unwritten(tmp_path):
    """`StageSpec.optional`: the stage may leave it unwritten (round 1's network where the photos pass through);
    the record lists what was written, the stages after it see only that, and a committed one the next run
    leaves unwritten is removed as the stage's own. The others stay required."""
    st = tmp_path / "st"

    def writes(with_d: bool):
        def fn(ctx):
            (ctx.work_dir / "a.txt").write_text("a")
            if with_d:
                (ctx.work_dir / "d").mkdir()
                (ctx.work_dir / "d" / "b.txt").write_text("b")
            return {"d": with_d}
        return fn

    runner = StageRunner()
    full = runner.run(_spec(tmp_path, writes(True), optional=("d",), settings={"d": True}))
    assert set(full.outputs) == {"a.txt", "d"} and (st / "d" / "b.txt").is_file()
    bare = runner.run(_spec(tmp_path, writes(False), optional=("d",), settings={"d": False}))
    assert not bare.skipped and set(bare.outputs) == {"a.txt"} and not (st / "d").exists()
    rec = json.loads((st / "stages" / "s.json").read_text())
    assert set(rec["manifest"]["outputs"]) == {"a.txt"} and set(rec["owned"]) == {"a.txt"}
    again = runner.run(_spec(tmp_path, writes(False), optional=("d",), settings={"d": False}))
    assert again.skipped and set(again.outputs) == {"a.txt"} and again.outputs_digest == bare.outputs_digest
    # Without `optional` every declared output is required: a run that leaves one unwritten is refused.
    with pytest.raises(DgsError, match=r"\['d'\]"):
        runner.run(_spec(tmp_path, writes(False), settings={"d": False}))
    # A user's file where the optional output would go is not the stage's: a run that would remove it stops.
    (st / "d").mkdir()
    (st / "d" / "mine.txt").write_text("user")
    with pytest.raises(UnownedOutputError, match="mine.txt"):
        runner.run(_spec(tmp_path, writes(False), optional=("d",), settings={"d": "changed"}))
    assert (st / "d" / "mine.txt").read_text() == "user"
    with pytest.raises(ValueError, match="optional"):
        _spec(tmp_path, writes(False), optional=("e",))


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

    fast = PRESETS["fast"].align
    cfg = align_config(fast, seed=3)
    assert cfg.points_budget == fast.points != PREVIEW.points_budget
    assert cfg.max_size_px == PREVIEW.max_size_px and cfg.seed == 3
    default = align_config(PRESETS["default"].align, seed=0)
    assert default.points_budget == AlignConfig().points_budget  # None keeps the preset's
    over = align_config(dataclasses.replace(fast, points=1234, iters=7, max_size_px=99), seed=0)
    assert (over.points_budget, over.align.iters, over.max_size_px) == (1234, 7, 99)


def test_round_settings_are_the_component_configs():
    """Each stage gets the config its component runs, with the stage's seed; round 1 has no round-2 rules."""
    from denoise.n2v import N2V_PRESETS
    from denoise.round2 import Round2Config
    from splat.train import TRAIN_PRESETS

    cfg = preset("fast", rounds=2, seed=5)
    r1, r2 = round_settings(cfg, 1), round_settings(cfg, 2)
    assert r1.denoise.n2v == dataclasses.replace(N2V_PRESETS["fast"], method="n2v")
    assert r1.denoise.passes == cfg.denoise.passes and r1.render.device == cfg.device
    assert r1.splat.train == dataclasses.replace(TRAIN_PRESETS["instantsplat"], seed=r1.splat.train.seed)
    assert r1.splat.train.seed != r2.splat.train.seed != r2.align.align.seed  # each stage its own seed
    assert (r1.align.reuse_intrinsics, r1.align.reuse_geometry) == (None, None)
    assert (r2.align.reuse_intrinsics, r2.align.reuse_geometry) == ("auto", "auto")
    assert r1.select is None and r1.refine is None and r2.denoise is None
    assert (r2.select.views, r2.select.select_views) == (cfg.views, True)
    assert r2.refine.round2 == Round2Config(steps=cfg.denoise.round2_steps)
    assert r1.fuse is None and r1.splat.noisy_detail.weight == 0.5  # `fast` takes the noisy band, no fusion
    fused = round_settings(dataclasses.replace(cfg, fuse_noisy_splat=True), 1)
    assert fused.fuse is not None and fused.fuse.train.seed != fused.splat.train.seed
    charb = round2_config(DenoiseSettings(round2_loss="charbonnier"))
    assert charb.loss == "charbonnier" and round2_config(DenoiseSettings()).loss == Round2Config().loss
    assert train_config(SplatSettings(preset="quick", iters=17), seed=2).iters == 17


@pytest.mark.parametrize(("change", "key"), [
    ({"denoise": DenoiseSettings(n2v_preset="turbo")}, "denoise.n2v_preset"),
    ({"denoise": DenoiseSettings(round2_preset="turbo")}, "denoise.round2_preset"),
    ({"align": AlignSettings(preset="turbo")}, "align.preset"),
    ({"splat": SplatSettings(preset="turbo")}, "splat.preset"),
])
def test_unknown_component_presets_are_config_errors(change, key):
    with pytest.raises(ConfigError, match=key) as exc:
        check_settings(dataclasses.replace(preset("fast", rounds=2), **change))
    assert "turbo" in str(exc.value)


def test_dataclass_settings_reach_the_stage_and_key_by_their_json(tmp_path):
    @dataclasses.dataclass(frozen=True)
    class Inner:
        size_px: int

    @dataclasses.dataclass(frozen=True)
    class Settings:
        inner: Inner
        name: str

    seen = []

    def fn(ctx):
        seen.append(ctx.settings)
        (ctx.work_dir / "a.txt").write_text(ctx.settings.name)
        return {}

    def spec(settings):
        return StageSpec("s", tmp_path / "st", fn, ("a.txt",), settings=settings)

    settings = Settings(Inner(3), "x")
    res = StageRunner().run(spec(settings))
    assert seen == [settings]  # the object itself, not a flattened dict
    assert settings_json(settings) == {"inner": {"size_px": 3}, "name": "x"}
    record = json.loads((tmp_path / "st" / "stages" / "s.json").read_text())
    assert record["settings"] == {"inner": {"size_px": 3}, "name": "x"}
    # The key is that of the canonical JSON: an equal mapping keys alike, a nested change does not.
    assert spec({"name": "x", "inner": {"size_px": 3}}).key() == res.key == spec(Settings(Inner(3), "x")).key()
    assert spec(Settings(Inner(4), "x")).key() != res.key
    assert StageRunner().run(spec(Settings(Inner(3), "x"))).skipped and len(seen) == 1
    with pytest.raises(TypeError, match="canonical JSON"):
        settings_json({"f": object()})
    with pytest.raises(TypeError, match="dataclass instance or a mapping"):
        settings_json(3)


def test_file_hashes_against_hashlib(tmp_path):
    big = tmp_path / "big.bin"
    big.write_bytes(bytes(range(256)) * 9000)  # over one read chunk
    assert file_sha256(big) == hashlib.sha256(big.read_bytes()).hexdigest()
    (tmp_path / "sub" / ".hidden").mkdir(parents=True)
    for rel in ("sub/z.txt", "sub/.hidden/h.txt", ".top.txt", "a.txt"):
        (tmp_path / rel).write_text(rel)
    assert [p.relative_to(tmp_path).as_posix() for p in tree_files(tmp_path)] == ["a.txt", "big.bin", "sub/z.txt"]


def test_the_best_preset_trains_the_wide_unet():
    """`best` is `default` with the wide UNet (width 32); `default` keeps width 16. Both splat for 2000
    iterations, `fast` for InstantSplat's 1000."""
    from denoise.n2v import N2V_PRESETS

    best, default = round_settings(preset("best"), 1), round_settings(preset("default"), 1)
    assert best.denoise.n2v.unet.width == N2V_PRESETS["wide"].unet.width == 32
    assert default.denoise.n2v.unet.width == N2V_PRESETS["default"].unet.width == 16
    assert dataclasses.replace(best.denoise.n2v, unet=default.denoise.n2v.unet) == default.denoise.n2v
    assert best.splat == default.splat and default.splat.train.iters == 2000
    assert round_settings(preset("fast"), 1).splat.train.iters == 1000


def test_only_marked_work_folders_are_removed_as_stale(tmp_path):
    from eval.pipeline.stage import WORK_MARKER, stage_work_dir

    users = tmp_path / ".splat.work-abcdefgh"  # the runner's name pattern, but the user's folder
    users.mkdir()
    (users / "thesis.tex").write_text("x")
    stale = tmp_path / ".splat.work-zyxwvuts"  # left by a killed run: marked
    stale.mkdir()
    (stale / WORK_MARKER).write_text("stage splat\n")
    with stage_work_dir(tmp_path, "splat") as work:
        assert (work / WORK_MARKER).is_file()
    assert (users / "thesis.tex").read_text() == "x" and not stale.exists() and not work.exists()
