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
