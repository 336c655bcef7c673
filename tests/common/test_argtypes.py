"""`mvgeo.common.argtypes.out_path` on every command line that takes `--out`."""

from pathlib import Path

import pytest


@pytest.mark.parametrize(("module", "argv"), [
    ("mvgeo.cli", ["align", "IMAGES", "--out", ""]),
    ("mvgeo.cli", ["colmap", "IMAGES", "--out", " "]),
    ("eval.cli", ["run", "IMAGES", "--out", ""]),
    ("eval.cli", ["eval", "llff_like", "--out", ""]),
    ("eval.cli", ["cost", "llff_like", "--out", ""]),
    ("eval.cli", ["dataset", "import", "dtu", "IMAGES", "--out", ""]),
    ("data_synth.cli", ["render", "llff_like", "--out", ""]),
    ("splat.cli", ["export", "IMAGES/x.ply", "--out", ""]),
    ("denoise.cli", ["n2v", "IMAGES", "--out", ""]),
    ("denoise.cli", ["select", "IMAGES", "--images", "IMAGES", "--out", ""]),
])
def test_an_empty_out_is_a_usage_error_everywhere(tmp_path, monkeypatch, capsys, module, argv):
    """`--out ""` (an unset shell variable) is refused by the parser, exit 2, and nothing is written to the
    current folder, which `Path("")` would name."""
    import importlib

    from mvgeo.common.argtypes import out_path

    images = tmp_path / "images"
    images.mkdir()
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    main = importlib.import_module(module).main
    try:
        code = main([a.replace("IMAGES", str(images)) for a in argv])
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    assert "argument --out: is empty" in capsys.readouterr().err
    assert list(cwd.iterdir()) == [] and list(images.iterdir()) == []
    assert out_path("a/b") == Path("a/b")


@pytest.mark.parametrize(("text", "ok"), [("0", True), ("0.5", True), ("0.999", True), ("1", False), ("-0.1", False),
                                          ("nan", False), ("inf", False), ("half", False)])
def test_half_open_fraction(text, ok):
    import argparse

    from mvgeo.common.argtypes import half_open_fraction

    if ok:
        assert half_open_fraction(text) == float(text)
    else:
        with pytest.raises(argparse.ArgumentTypeError):
            half_open_fraction(text)


def test_keep_noisy_is_checked_as_the_option_the_user_typed(capsys):
    from eval.cli import main

    try:
        code = main(["run", "IMAGES", "--out", "O", "--keep-noisy", "-1"])
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2 and "argument --keep-noisy: must be a number in [0, 1)" in err and "denoise.keep_noisy" not in err
