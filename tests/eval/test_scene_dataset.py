"""`eval.evaluate.scene_dataset`: a scene rendered into an evaluation folder is reused only while it is the same
scene (the file edited, or another file of the same name, renders it again)."""

from __future__ import annotations

import shutil
from pathlib import Path

from data_synth.scene_file import builtin_dir
from eval.evaluate import scene_dataset
from eval.pipeline.hashing import hash_path

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
    assert sorted(p.name for p in (out / "data").iterdir() if not p.name.startswith(".")) == [Path(folder).name]
