"""`mvgeo` refuses bad input with exit 2, no traceback, inputs untouched and nothing left behind:
numeric options, a broken symlinked photo, models with no image in common, a corrupt cameras.bin;
and SIGTERM during `mvgeo align` exits 143 with one line, no native stack dump."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvgeo.camera import Camera
from mvgeo.cli import main
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import list_images, write_image
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model
from tests.common.cli_contract import assert_refused


@pytest.fixture
def images(tmp_path, rng):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(3):
        write_image(folder / f"v{i}.png", rng.random((24, 32, 3)).astype(np.float32))
    return folder


def _model(names, rng) -> SparseModel:
    cams = {1: Camera.pinhole(40.0, 40.0, 16.0, 12.0, 32, 24)}
    images = [PosedImage(n, 1, np.hstack([Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix(),
                                          rng.normal(size=(3, 1))])) for n in names]
    return SparseModel(cams, images, rng.normal(size=(4, 3)), rng.integers(0, 256, (4, 3)).astype(np.uint8))


@pytest.mark.parametrize(("option", "value"), [
    ("--max-size", "8"), ("--max-size", "abc"), ("--pointmap-size", "0"), ("--iters", "-1"),
    ("--align-stride", "0"), ("--points", "0"), ("--points", "-5")])
def test_align_numeric_options_are_checked_by_the_parser(images, tmp_path, capsys, option, value):
    out = tmp_path / "out"
    assert_refused(main, ["align", images, "--out", out, option, value], capsys, inputs=[images], watch=[tmp_path],
                   message=f"argument {option}")


def test_broken_symlinked_photo_is_an_error_naming_it(images, tmp_path, capsys):
    link = images / "v9.png"
    link.symlink_to(tmp_path / "gone" / "v9.png")
    with pytest.raises(InputError) as info:
        list_images(images)
    assert info.value.path == link
    out = tmp_path / "out"
    assert_refused(main, ["align", images, "--out", out], capsys, inputs=[images], watch=[tmp_path],
                   message=["v9.png", "broken symbolic link", "fix:"])


def test_a_symlink_to_a_photo_is_listed(images, tmp_path):
    (images / "v5.png").symlink_to(images / "v0.png")
    assert [p.name for p in list_images(images)] == ["v0.png", "v1.png", "v2.png", "v5.png"]


def test_compare_with_no_common_image_names(tmp_path, rng, capsys):
    est, ref = tmp_path / "est", tmp_path / "ref"
    write_sparse_model(est, _model(["a.png", "b.png", "c.png"], rng), binary=True)
    write_sparse_model(ref, _model(["x.png", "y.png", "z.png"], rng), binary=False)
    err = assert_refused(main, ["compare", est, ref], capsys, inputs=[est, ref], watch=[tmp_path],
                         message=["no image names in common", "fix:"])
    assert "nan" not in err.lower()


def test_compare_with_common_names_still_works(tmp_path, rng, capsys):
    est, ref = tmp_path / "est", tmp_path / "ref"
    write_sparse_model(est, _model(["a.png", "b.png", "c.png"], rng), binary=True)
    write_sparse_model(ref, _model(["a.png", "b.png", "c.png"], rng), binary=True)
    capsys.readouterr()
    assert main(["compare", str(est), str(ref), "--json"]) == 0
    assert '"n_registered": 3' in capsys.readouterr().out


def test_compare_names_a_file_given_for_a_model_folder(tmp_path, rng, capsys):
    est = tmp_path / "est"
    write_sparse_model(est, _model(["a.png", "b.png", "c.png"], rng), binary=True)
    ref = tmp_path / "ref.txt"
    ref.write_text("not a model")
    assert_refused(main, ["compare", est, ref], capsys, inputs=[est, ref], watch=[tmp_path],
                   message=[str(ref), "is a file, not a COLMAP model folder", "fix:"])


def test_compare_json_is_strict_json_and_one_shared_image_is_refused(tmp_path, rng, capsys):
    """Two shared views determine relative rotations but no ATE: --json prints null for it (standard JSON has
    no NaN), the text output nan; one shared view determines nothing and is refused."""
    import json

    est, ref = tmp_path / "est", tmp_path / "ref"
    write_sparse_model(est, _model(["a.png", "b.png", "c.png"], rng), binary=True)
    write_sparse_model(ref, _model(["a.png", "b.png", "x.png"], rng), binary=True)
    capsys.readouterr()
    assert main(["compare", str(est), str(ref), "--json"]) == 0
    text = capsys.readouterr().out
    out = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert out["n_registered"] == 2 and None in out.values() and "NaN" not in text
    assert all(v is None or not isinstance(v, float) or np.isfinite(v) for v in out.values())
    write_sparse_model(ref, _model(["a.png", "y.png", "z.png"], rng), binary=True)
    assert_refused(main, ["compare", est, ref], capsys, inputs=[est, ref], watch=[tmp_path],
                   message=["one image in common", "a.png", "fix:"])


def _corruptions(good: bytes) -> dict[str, bytes]:
    return {
        "empty": b"",
        "truncated": good[: len(good) // 2],
        "random": np.random.default_rng(5).integers(0, 256, len(good), dtype=np.uint8).tobytes(),
        "unknown_model": good[:12] + (99).to_bytes(4, "little") + good[16:],
        "huge_count": (10**12).to_bytes(8, "little") + good[8:],
        "trailing": good + b"\0" * 5,
    }


@pytest.mark.parametrize("kind", ["empty", "truncated", "random", "unknown_model", "huge_count"])
def test_corrupt_cameras_bin_names_the_file_with_a_fix(tmp_path, rng, capsys, kind):
    from mvgeo.sparse_model import cameras_bin_problem

    est, ref = tmp_path / "est", tmp_path / "ref"
    write_sparse_model(est, _model(["a.png", "b.png", "c.png"], rng), binary=True)
    write_sparse_model(ref, _model(["a.png", "b.png", "c.png"], rng), binary=True)
    good = (est / "cameras.bin").read_bytes()
    assert cameras_bin_problem(est / "cameras.bin") is None
    (est / "cameras.bin").write_bytes(_corruptions(good)[kind])
    err = assert_refused(main, ["compare", est, ref], capsys, inputs=[est, ref], watch=[tmp_path],
                         message=[str(est / "cameras.bin"), "corrupt COLMAP cameras file", "fix:"])
    assert "Check failed" not in err and "reconstruction.cc" not in err


def test_cameras_bin_problem_against_the_layout(tmp_path, rng):
    """The structural check agrees with pycolmap on sound files of every camera model we write
    and finds each corruption."""
    from mvgeo.sparse_model import cameras_bin_problem

    model = _model(["a.png"], rng)
    model.cameras[2] = Camera("OPENCV", 320, 240, [250.0, 251.0, 160.0, 120.0, 0.01, -0.002, 1e-4, -2e-4])
    model.cameras[3] = Camera("SIMPLE_RADIAL", 64, 48, [50.0, 32.0, 24.0, 0.01])
    write_sparse_model(tmp_path, model, binary=True)
    good = (tmp_path / "cameras.bin").read_bytes()
    assert cameras_bin_problem(tmp_path / "cameras.bin") is None
    assert len(read_sparse_model(tmp_path).cameras) == 3
    for kind, data in _corruptions(good).items():
        (tmp_path / "cameras.bin").write_bytes(data)
        assert cameras_bin_problem(tmp_path / "cameras.bin") is not None, kind


def test_sigterm_during_align_exits_cleanly(tmp_path):
    """SIGTERM once the alignment runs: exit 143, one line, no native stack dump, nothing left."""
    from data_synth import render_scene

    scene = render_scene("llff_like", tmp_path / "scene", size_wh=(128, 96), views=4)
    work = tmp_path / "work"
    work.mkdir()
    out, log = work / "out", tmp_path / "stderr.txt"
    env = {**os.environ, "DGS_NO_PROGRESS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
    # --iters makes the global alignment last long enough to be interrupted inside it.
    cmd = [sys.executable, "-m", "mvgeo.cli", "align", str(scene / "images"), "--out", str(out),
           "--iters", "1000000", "-v"]
    with open(log, "wb") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
        try:
            deadline = time.monotonic() + 60
            while "stage loop_check" not in log.read_text() and time.monotonic() < deadline:
                assert proc.poll() is None, log.read_text()
                time.sleep(0.05)
            assert "stage loop_check" in log.read_text(), "the alignment did not start"
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
    text = log.read_text()
    assert code == 128 + signal.SIGTERM, text
    assert "*** " not in text and "stack trace" not in text and "Traceback" not in text, text
    assert text.strip().splitlines()[-1] == "terminated (SIGTERM)"
    assert os.listdir(work) == []  # no output, no temporary folder
