"""`data-synth render --out` and `write_dataset`: the output policy (mvgeo.common.output).

Every refusal exits 2 before rendering, prints no traceback, leaves every file byte-identical and
no temporary behind.
"""

from __future__ import annotations

import json
import os

import pytest

from data_synth import load_scene, render_scene, write_dataset
from data_synth.cli import main
from mvgeo.common.errors import InputError
from mvgeo.common.output import MANIFEST_NAME
from tests.common._out_policy import assert_refused, fake_previous_output, readonly_access, snapshot

TINY = ["--size", "32x24", "--views", "2"]


def test_render_into_a_folder_with_a_user_file(tmp_path, capsys):
    p = tmp_path / "p"
    p.mkdir()
    (p / "thesis.tex").write_text("x")
    for extra in ([], ["--overwrite"]):
        assert_refused(main, ["render", "llff_like", "--out", p, *TINY, *extra], capsys, tmp_path,
                       "did not write", "thesis.tex")


def test_render_existing_file_other_output_and_read_only_parent(tmp_path, capsys, monkeypatch):
    f = tmp_path / "data.bin"
    f.write_bytes(b"\x00\x01")
    assert_refused(main, ["render", "llff_like", "--out", f, "--overwrite", *TINY], capsys, tmp_path, "not a folder")
    assert not list(tmp_path.glob(".data.bin.old-*"))
    other = fake_previous_output(tmp_path / "al", "mvgeo align")
    assert_refused(main, ["render", "llff_like", "--out", other, "--overwrite", *TINY], capsys, tmp_path,
                   "output of `mvgeo align`")
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    assert_refused(main, ["render", "llff_like", "--out", ro / "ds", *TINY], capsys, tmp_path, "not writable")


def test_render_out_holding_the_scene_file(tmp_path, capsys):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    scene = scenes / "s.toml"
    scene.write_text('base = "llff_like"\n')
    assert_refused(main, ["render", scene, "--out", scenes, *TINY], capsys, tmp_path, "contains the input")


def test_render_out_dot(tmp_path, capsys, monkeypatch):
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.md").write_text("n")
    monkeypatch.chdir(user)
    assert_refused(main, ["render", "llff_like", "--out", ".", *TINY], capsys, tmp_path, "did not write")
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.chdir(empty)
    assert main(["render", "llff_like", "--out", ".", *TINY]) == 0  # an empty current folder is filled
    assert (empty / "split.json").is_file() and os.getcwd() == str(empty)
    assert not [p for p in os.listdir(empty) if ".tmp-" in p]


def test_render_previous_output_needs_overwrite(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["render", "llff_like", "--out", str(out), *TINY, "--seed", "1"]) == 0
    assert json.loads((out / MANIFEST_NAME).read_text())["command"] == "data-synth render"
    err = assert_refused(main, ["render", "llff_like", "--out", out, *TINY], capsys, tmp_path, "previous output")
    assert "--overwrite" in err
    assert main(["render", "llff_like", "--out", str(out), *TINY, "--seed", "2", "--overwrite"]) == 0
    assert json.loads((out / "meta.json").read_text())["seed"] == 2  # replaced
    assert sorted(os.listdir(tmp_path)) == ["ds"]


def test_library_writer_refuses_by_default(tmp_path):
    out = render_scene("llff_like", tmp_path / "ds", size_wh=(32, 24), views=2)
    before = snapshot(tmp_path)
    with pytest.raises(InputError, match="previous output"):
        render_scene("llff_like", out, size_wh=(32, 24), views=2)
    user = tmp_path / "user"
    user.mkdir()
    (user / "keep.txt").write_text("k")
    spec = load_scene("llff_like", size_wh=(32, 24), views=2)
    with pytest.raises(InputError, match="did not write"):
        write_dataset(spec, user, overwrite=True)
    assert snapshot(tmp_path) == {**before, "user": None, "user/keep.txt": snapshot(tmp_path)["user/keep.txt"]}
    render_scene("llff_like", out, size_wh=(32, 24), views=2, seed=5, overwrite=True)
    assert json.loads((out / "meta.json").read_text())["seed"] == 5
