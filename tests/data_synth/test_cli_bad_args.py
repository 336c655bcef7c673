"""`data-synth` refuses bad numeric options in the parser and renders that do not fit in memory before
any work (exit 2, no traceback, nothing left behind); the memory estimate against a measurement."""

import tracemalloc

import pytest

import data_synth.render
from data_synth.cli import main
from data_synth.dataset import render_needs
from data_synth.intrinsics import camera_from_spec
from data_synth.render import SceneRenderer
from data_synth.rigs import rig_views
from data_synth.scene_file import load_scene
from mvgeo.common.errors import InputError
from tests.common.cli_contract import assert_refused

GiB = 2**30


@pytest.fixture
def no_render(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("rendering started before the check")

    monkeypatch.setattr(SceneRenderer, "from_spec", fail)


@pytest.mark.parametrize(("option", "value"), [
    ("--size", "0x5"), ("--size", "5x0"), ("--size", "7x100"), ("--size", "8193x100"), ("--size", "504"),
    ("--size", "-5x5"), ("--views", "0"), ("--views", "-1"), ("--seed", "-1"), ("--seed", str(2**32))])
def test_render_numeric_options(tmp_path, capsys, no_render, option, value):
    assert_refused(main, ["render", "llff_like", "--out", tmp_path / "out", option, value], capsys, inputs=[],
                   watch=[tmp_path], message=f"argument {option}")


def test_show_checks_the_size_too(capsys):
    assert_refused(main, ["show", "llff_like", "--size", "0x5"], capsys, inputs=[], watch=[],
                   message="argument --size")


@pytest.mark.parametrize("size", ["8192x8192", "2048x1536"])
def test_render_that_does_not_fit_is_refused_before_any_work(tmp_path, capsys, monkeypatch, no_render, size):
    """8192x8192 with 2x2 rays needs ~72 GiB; with 24 GiB (or 0.5 GiB for 2048x1536) it must be refused."""
    from data_synth.render import estimate_render_bytes

    monkeypatch.setattr(data_synth.render, "available_memory_bytes", lambda: 24 * GiB if size[0] == "8" else GiB // 2)
    user_file = tmp_path / "notes.txt"
    user_file.write_text("keep me")
    err = assert_refused(main, ["render", "llff_like", "--size", size, "--views", "2", "--out", tmp_path / "out"],
                         capsys, inputs=[user_file], watch=[tmp_path],
                         message=["GiB of memory", "is available", "fix:", "--size"])
    w, h = (int(v) for v in size.split("x"))
    assert f"{estimate_render_bytes((w, h), 2) / GiB:.1f} GiB" in err


def test_render_that_fits_goes_ahead(tmp_path, monkeypatch):
    monkeypatch.setattr(data_synth.render, "available_memory_bytes", lambda: 1 * GiB)
    assert main(["render", "llff_like", "--size", "64x48", "--views", "2", "--out", str(tmp_path / "out")]) == 0
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == ["view_000.png", "view_001.png"]


def test_check_render_memory_quotes_a_size_that_fits():
    from data_synth.render import check_render_memory, estimate_render_bytes

    spec = load_scene("llff_like", size_wh=(4000, 3000), views=2)
    need = estimate_render_bytes((4000, 3000), spec.render.supersample)
    with pytest.raises(InputError) as info:
        check_render_memory(spec, available_bytes=need // 4)
    fit = info.value.fix.split("--size ")[1].split(" ")[0]
    w, h = (int(v) for v in fit.split("x"))
    assert 1900 <= w <= 2000 and 1400 <= h <= 1500  # half the sides: a quarter of the memory
    assert estimate_render_bytes((w, h), spec.render.supersample) <= need // 4
    assert check_render_memory(spec, available_bytes=need) == need


def test_estimate_bounds_a_measured_render():
    """The estimate covers the numpy allocations of one view (tracemalloc) plus Open3D's hit records
    (32 B per ray, not seen by tracemalloc), and is not more than twice that."""
    from data_synth.render import estimate_render_bytes

    w, h = 160, 120
    spec = load_scene("llff_like", size_wh=(w, h), views=2)
    n = spec.render.supersample
    needs = render_needs(spec)
    renderer = SceneRenderer.from_spec(spec)
    view = rig_views(spec.rig)[0]
    camera = camera_from_spec(spec.camera, (w, h))
    tracemalloc.start()
    try:
        renderer.render(camera, view.cam_from_world, supersample=n, depth=needs.depth, alpha=needs.alpha,
                        normals=needs.normals)
        numpy_peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    measured = numpy_peak + 32 * w * h * n * n
    estimate = estimate_render_bytes((w, h), n)
    assert measured <= estimate <= 2 * measured, (measured, estimate)


@pytest.mark.parametrize("command", ["render", "show"])
@pytest.mark.parametrize(("name", "content"), [("scene.toml", b'[scene]\nname = "caf\xe9"\n'),
                                             ("photo.png", b"\x89PNG\r\n\x1a\n\xff\xfe")])
def test_a_scene_file_that_is_not_utf8_is_refused(tmp_path, capsys, no_render, command, name, content):
    scene = tmp_path / "in" / name
    scene.parent.mkdir()
    scene.write_bytes(content)
    argv = [command, scene] + (["--out", tmp_path / "out"] if command == "render" else [])
    assert_refused(main, argv, capsys, inputs=[scene], watch=[tmp_path, scene.parent],
                   message=[str(scene), "not a UTF-8 text file", "fix:"])


def test_a_scene_without_training_views_or_with_up_along_the_view_is_refused(tmp_path, capsys):
    """One view is a test view under the LLFF split (nothing left to train on); an `up` along the viewing
    direction has no camera. Both were found only while rendering (exit 0 with an unusable split, or exit 1
    without the key)."""
    assert_refused(main, ["render", "llff_like", "--views", "1", "--size", "32x24", "--out", tmp_path / "o1"],
                   capsys, inputs=[], watch=[tmp_path], message=["key 'split'", "none of the 1 view(s) for training"])
    scene = tmp_path / "up.toml"
    scene.write_text('base = "llff_like"\n[rig]\nup = [0, 1, 0]\nlook_at = [0, 4, 1.2]\n')
    for command in (["render", scene, "--views", "3", "--size", "48x36", "--out", tmp_path / "o2"], ["show", scene]):
        assert_refused(main, command, capsys, inputs=[scene], watch=[tmp_path],
                       message=[str(scene), "key 'rig.up'", "parallel to the viewing direction"])
