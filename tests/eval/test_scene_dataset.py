"""`eval.evaluate.scene_dataset`: a scene rendered into an evaluation folder is reused only while it is the same
scene (the file edited, or another file of the same name, renders it again)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from data_synth.scene_file import builtin_dir
from eval.evaluate import scene_dataset
from eval.pipeline.hashing import hash_path
from eval.pipeline.stage import RECORD_DIR

ARGS = dict(size_wh=(64, 48), views=4)


def test_a_rendered_scene_is_reused_while_it_is_the_same_scene(tmp_path):
    scene = tmp_path / "mine" / "myscene.toml"
    scene.parent.mkdir()
    shutil.copy(builtin_dir() / "llff_like.toml", scene)
    out = tmp_path / "eval"
    name, folder = scene_dataset("scene_file", scene, out, **ARGS)
    assert name == "myscene" and (folder / "split.json").is_file()
    first = hash_path(folder)
    stamp = (folder / "split.json").stat().st_mtime_ns

    assert scene_dataset("scene_file", scene, out, **ARGS)[1] == folder  # unchanged: reused as it is
    assert (folder / "split.json").stat().st_mtime_ns == stamp and hash_path(folder) == first

    text = scene.read_text()
    assert "sigma_8bit = 25.0" in text
    scene.write_text(text.replace("sigma_8bit = 25.0", "sigma_8bit = 2.0"))  # the user edits the scene
    scene_dataset("scene_file", scene, out, **ARGS)
    assert "sigma_8bit = 2.0" in (folder / "scene.toml").read_text()
    edited = hash_path(folder)
    assert edited != first

    other = tmp_path / "other" / "myscene.toml"  # another scene under the same name
    other.parent.mkdir()
    shutil.copy(builtin_dir() / "object_ring.toml", other)
    scene_dataset("scene_file", other, out, **ARGS)
    assert hash_path(folder) not in (first, edited)
    assert sorted(p.name for p in (out / "data").iterdir() if not p.name.startswith(".")) == [Path(folder).name,
                                                                                              RECORD_DIR]


def test_a_rendered_scene_is_rendered_again_by_changed_renderer_code(tmp_path):
    """The render's record holds the renderer's source digest: a scene rendered by other code (an edited
    degradation, or a render from before the record) is rendered again; the same code gives the same data (the
    photos, cameras and split; meta.json records the render's timings too)."""
    out = tmp_path / "eval"
    _, folder = scene_dataset("builtin", "llff_like", out, **ARGS)
    record = out / "data" / RECORD_DIR / f"{folder.name}.render.json"

    def data():
        return [hash_path(folder / part) for part in ("images", "clean", "depth", "sparse", "split.json")]

    first, stamp = data(), (folder / "split.json").stat().st_mtime_ns
    rec = json.loads(record.read_text())
    record.write_text(json.dumps({**rec, "code": {"data_synth": "0" * 64}}))  # as if rendered by other code
    scene_dataset("builtin", "llff_like", out, **ARGS)
    assert (folder / "split.json").stat().st_mtime_ns != stamp and data() == first
    assert json.loads(record.read_text()) == rec
    stamp = (folder / "split.json").stat().st_mtime_ns
    record.unlink()  # a render from before the record: the code that made it is unknown
    scene_dataset("builtin", "llff_like", out, **ARGS)
    assert (folder / "split.json").stat().st_mtime_ns != stamp and record.is_file()
    stamp = (folder / "split.json").stat().st_mtime_ns
    scene_dataset("builtin", "llff_like", out, **ARGS)  # same scene, same code: reused
    assert (folder / "split.json").stat().st_mtime_ns == stamp
