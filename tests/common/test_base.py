import os
import pickle

import numpy as np
import pytest

from mvgeo.common import ConfigError, InputError, ShapeError, StageTimer, atomic_output_dir, check_shape
from mvgeo.common.errors import AlignmentRefusedError, DisconnectedViewsError, UnposedViewsError
from mvgeo.common.imageio import list_images, read_image, write_image
from mvgeo.common.output import MANIFEST_NAME, prepare_output, read_manifest


def test_input_error_names_path_and_fix(tmp_path):
    err = InputError("cannot decode image", path=tmp_path / "x.png", fix="re-export it")
    assert "x.png" in str(err) and "re-export it" in str(err)


def test_config_error_names_key():
    err = ConfigError("unknown key", key="cameras.rig.radus", path="scene.toml", expected="one of radius, count")
    assert "cameras.rig.radus" in str(err) and "scene.toml" in str(err)


@pytest.mark.parametrize("err", [
    ConfigError("unknown key", key="a.b", path="scene.toml", expected="c"),
    AlignmentRefusedError("the focal is not determined", kind="focal", views=("v1",), fix="add photos"),
    UnposedViewsError("no pair reaches them", views=[2], names=None),
    DisconnectedViewsError("not connected", views=("v3",), path="images", fix="add photos"),
    InputError("bad", path="x.png", fix="re-export it"),
])
def test_errors_pickle_as_themselves(err):
    """A Ray task's error reaches the driver pickled: the same type, message and attributes, even where the
    constructor takes keyword-only arguments."""
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is type(err) and str(back) == str(err) and vars(back) == vars(err)


def test_check_shape():
    check_shape(np.zeros((2, 5, 3, 3)), ["*", 3, 3])
    check_shape(np.zeros((4, 2)), ["N", 2])
    with pytest.raises(ShapeError, match="expected shape"):
        check_shape(np.zeros((4, 3)), ["N", 2])
    with pytest.raises(ShapeError):
        check_shape(np.zeros((3,)), ["*", 3, 3])


def test_atomic_dir_success_and_failure(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(prepare_output(out, command="test cmd")) as tmp:
        (tmp / "a.txt").write_text("1")
        assert not out.exists()
    assert (out / "a.txt").read_text() == "1"
    assert read_manifest(out)["command"] == "test cmd"
    plan = prepare_output(out, command="test cmd", overwrite=True)
    with pytest.raises(RuntimeError), atomic_output_dir(plan) as tmp:
        (tmp / "b.txt").write_text("2")
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temp left behind
    assert not (out / "b.txt").exists() and (out / "a.txt").exists()  # old output untouched
    with atomic_output_dir(plan) as tmp:  # a previous output of the same command, with overwrite
        (tmp / "b.txt").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST_NAME, "b.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_stage_timer():
    t = StageTimer()
    with t.stage("a"):
        pass
    with t.stage("a"):
        pass
    d = t.as_dict()
    assert set(d) == {"a", "total"} and d["a"] >= 0


@pytest.mark.parametrize("bits", [8, 16])
def test_image_roundtrip(tmp_path, rng, bits):
    img = rng.random((7, 5, 3)).astype(np.float32)
    write_image(tmp_path / "a.png", img, bits=bits)
    back = read_image(tmp_path / "a.png")
    assert back.shape == (7, 5, 3) and back.dtype == np.float32
    # quantisation error is at most half a step
    assert np.abs(back - img).max() <= 0.5 / (2**bits - 1) + 1e-7


def test_image_errors(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="bad.png"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(InputError, match="does not exist"):
        list_images(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images"):
        list_images(empty)


def test_unreadable_image_or_folder_is_an_input_error(tmp_path, rng, monkeypatch):
    """What a file or folder without read permission raises (simulated: the tests may run as root, which
    permissions do not stop) becomes an InputError naming it, not a traceback."""
    write_image(tmp_path / "a.png", rng.random((4, 5, 3)))

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    with monkeypatch.context() as m:
        m.setattr(np, "fromfile", denied)
        with pytest.raises(InputError, match=r"a.png: cannot read the image file \(Permission denied\)"):
            read_image(tmp_path / "a.png")
    for method in ("iterdir", "is_file"):  # not readable; readable but not searchable
        with monkeypatch.context() as m:
            m.setattr(type(tmp_path), method, denied)
            with pytest.raises(InputError, match=r"cannot read the folder \(Permission denied\)"):
                list_images(tmp_path)


def test_grayscale_is_replicated(tmp_path):
    from mvgeo.common.deps import cv2

    cv2.imwrite(str(tmp_path / "g.png"), np.full((4, 6), 128, np.uint8))
    img = read_image(tmp_path / "g.png")
    assert img.shape == (4, 6, 3) and np.allclose(img, 128 / 255)


def test_write_image_replaces_the_file_instead_of_writing_into_it(tmp_path):
    # A hard link elsewhere (a `cp -al` backup) keeps the old bytes; a symbolic link is replaced, its target
    # untouched.
    img = np.full((4, 5, 3), 0.5, np.float32)
    path = tmp_path / "v.png"
    write_image(path, np.zeros((4, 5, 3), np.float32))
    backup = tmp_path / "backup.png"
    os.link(path, backup)
    old = backup.read_bytes()
    write_image(path, img)
    assert backup.read_bytes() == old and path.read_bytes() != old
    target = tmp_path / "user.txt"
    target.write_text("the user's")
    link = tmp_path / "l.png"
    link.symlink_to(target)
    write_image(link, img)
    assert target.read_text() == "the user's" and not link.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["backup.png", "l.png", "user.txt", "v.png"]


def test_list_images_refuses_a_file_name_that_is_not_utf8(tmp_path):
    write_image(tmp_path / "a.png", np.zeros((4, 4, 3), np.float32))
    (tmp_path / os.fsdecode(b"\xff_000.png")).write_bytes((tmp_path / "a.png").read_bytes())
    with pytest.raises(InputError, match="not UTF-8"):
        list_images(tmp_path)


def test_list_images_refuses_photos_it_cannot_read_unless_a_readable_copy_is_beside_them(tmp_path):
    """HEIC or raw photos would be left out without a word: refused, named, unless a JPEG/PNG of the same
    name is there (RAW+JPEG and HEIC+JPEG pairs read the JPEG). WebP is read."""
    from mvgeo.common.deps import cv2

    img = np.zeros((4, 4, 3), np.float32)
    write_image(tmp_path / "a.jpg", img)
    (tmp_path / "a.CR2").write_bytes(b"raw")  # the JPEG's raw twin
    (tmp_path / "b.HEIC").write_bytes(b"heic")
    with pytest.raises(InputError, match=r"1 photo\(s\) in a format this tool does not read \(b.HEIC\)") as e:
        list_images(tmp_path)
    assert "heif-convert" in e.value.fix
    (tmp_path / "b.HEIC").unlink()
    (tmp_path / "notes.txt").write_text("not a photo")  # other files are not photos: ignored as before
    assert [p.name for p in list_images(tmp_path)] == ["a.jpg"]
    assert cv2.imwrite(str(tmp_path / "c.webp"), np.zeros((4, 4, 3), np.uint8))
    assert [p.name for p in list_images(tmp_path)] == ["a.jpg", "c.webp"]
    only = tmp_path / "only"
    only.mkdir()
    for i in range(7):
        (only / f"IMG_{i}.heic").write_bytes(b"heic")
    with pytest.raises(InputError, match="7 photo.*IMG_4.heic and 2 more"):
        list_images(only)


def test_a_full_disk_is_a_message_not_a_traceback(capsys):
    import argparse
    import errno

    from mvgeo.common.cli import run_cli

    def full(args):
        raise OSError(errno.ENOSPC, "No space left on device", "/out/model.pt")

    assert run_cli(full, argparse.ArgumentParser(), []) == 1
    err = capsys.readouterr().err
    assert "no space left (disk full or quota exceeded) while writing /out/model.pt" in err and "fix:" in err, err

    def denied(args):
        raise OSError(errno.EACCES, "Permission denied", "/out")

    with pytest.raises(PermissionError):  # not a full disk: not this handler's
        run_cli(denied, argparse.ArgumentParser(), [])


def test_a_reader_that_stops_early_is_not_a_traceback():
    """`data-synth list | head -1`: the closed pipe ends the command quietly with 141 (128 + SIGPIPE)."""
    import subprocess
    import sys

    code = ("import argparse, sys\n"
            "from mvgeo.common.cli import run_cli\n"
            "def main(args):\n"
            "    for i in range(100000):\n"
            "        print('line', i)\n"
            "sys.exit(run_cli(main, argparse.ArgumentParser(), []))\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout.readline().startswith(b"line 0")
    proc.stdout.close()  # the reader stops, as `head -1` does
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


def test_a_broken_pipe_that_is_not_stdout_is_raised():
    """A command that writes to a dead subprocess's stdin fails: that is not a reader of its output stopping."""
    import argparse

    from mvgeo.common.cli import run_cli

    def main(args):
        raise BrokenPipeError(32, "Broken pipe")

    with pytest.raises(BrokenPipeError):
        run_cli(main, argparse.ArgumentParser(), [])
