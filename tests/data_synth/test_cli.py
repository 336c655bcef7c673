"""`data-synth` command line: list, show, render and exit codes."""

from __future__ import annotations

import pytest

from data_synth.cli import main, parse_size
from mvgeo.common.errors import InputError


def test_list_shows_every_builtin_on_one_line(capsys):
    assert main(["list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    names = [ln.split()[0] for ln in lines]
    assert {"llff_like", "llff_like_clean", "object_ring", "poisson", "hard_lowtexture", "hard_repetitive",
            "hard_tinybaseline", "hard_highnoise"} <= set(names)
    assert len(lines) == len(names)


def test_effects_and_show(capsys):
    assert main(["effects"]) == 0
    assert "poisson_gaussian" in capsys.readouterr().out
    assert main(["show", "llff_like", "--seed", "7", "--size", "100x80"]) == 0
    out = capsys.readouterr().out
    assert "seed = 7" in out and "size = [100, 80]" in out


def test_render(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["render", "llff_like", "--out", str(out), "--size", "32x24", "--views", "2", "--seed", "1"]) == 0
    assert sorted(p.name for p in (out / "images").iterdir()) == ["view_000.png", "view_001.png"]


@pytest.mark.parametrize("argv", [
    ["render", "nope", "--out", "x"],
    ["render", "llff_like", "--out", "x", "--size", "12by3"],
    ["render", "llff_like", "--out", "x", "--views", "0"],
    ["show", "llff_like", "--size", "4x4"],
])
def test_input_errors_exit_2_without_output(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    try:
        code = main(argv)
    except SystemExit as exc:  # option values are checked by the parser (usage message, then the error)
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


def test_bad_scene_key_exit_2_names_key(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('base = "llff_like"\n[render]\nsupersample = 99\n')
    assert main(["render", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "render.supersample" in err and str(bad) in err


def test_parse_size():
    assert parse_size("504x378") == (504, 378)
    with pytest.raises(InputError):
        parse_size("0x10")
