"""`splat train|render` refuse bad numeric options and devices before any work: exit 2, no traceback,
inputs byte-identical, no output or temporary folder left."""

import pytest
import torch

from splat.cli import main
from tests.common.cli_contract import assert_refused


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from data_synth import render_scene

    return render_scene("llff_like", tmp_path_factory.mktemp("data") / "llff", size_wh=(64, 48), views=3)


@pytest.fixture
def no_training(monkeypatch):
    """Any training or rendering means the check came too late."""
    import splat.cli

    def fail(*args, **kwargs):
        raise AssertionError("work started before the options were checked")

    monkeypatch.setattr(splat.cli, "train_gaussians", fail)
    monkeypatch.setattr(splat.cli, "render_views", fail)


@pytest.mark.parametrize(("option", "value"), [
    ("--depth-stride", "0"), ("--depth-stride", "-2"), ("--iters", "0"), ("--iters", "-1"), ("--iters", "ten"),
    ("--seed", "-1")])
def test_train_numeric_options(dataset, tmp_path, capsys, option, value):
    out = tmp_path / "out"
    assert_refused(main, ["train", dataset, "--out", out, "--init", "depth", option, value], capsys,
                   inputs=[dataset], watch=[tmp_path, dataset.parent], message=f"argument {option}")


@pytest.mark.parametrize(("device", "message"), [("banana", "unknown device"), ("cudaa", "unknown device"),
                                                 ("cuda", "CUDA is not available"),
                                                 ("cuda:1", "CUDA is not available")])
def test_train_device_is_checked_first(dataset, tmp_path, capsys, no_cuda, no_training, device, message):
    out = tmp_path / "out"
    assert_refused(main, ["train", dataset, "--out", out, "--init", "depth", "--iters", "2", "--device", device],
                   capsys, inputs=[dataset], watch=[tmp_path, dataset.parent], message=["--device", message])


def test_render_device_is_checked_first(dataset, tmp_path, capsys, no_cuda, no_training):
    model = tmp_path / "model.ply"
    model.write_bytes(b"ply\n")  # never read: the device is refused first
    out = tmp_path / "renders"
    assert_refused(main, ["render", model, "--cameras", dataset / "sparse" / "0", "--out", out, "--device", "cuda"],
                   capsys, inputs=[dataset, model], watch=[tmp_path], message="CUDA is not available")


def test_render_cuda_index_beyond_the_gpus(dataset, tmp_path, capsys, monkeypatch, no_training):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    model = tmp_path / "model.ply"
    model.write_bytes(b"ply\n")
    out = tmp_path / "renders"
    assert_refused(main, ["render", model, "--cameras", dataset / "sparse" / "0", "--out", out,
                          "--device", "cuda:3"], capsys, inputs=[dataset, model], watch=[tmp_path],
                   message="1 CUDA device")


def test_render_views_sharing_a_stem_are_refused(dataset, tmp_path, capsys, monkeypatch, no_training):
    """Renders are written as `<stem>.png`: two cameras named `v.png` and `v.jpg` would write one file."""
    import splat.cli
    from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model

    sparse = read_sparse_model(dataset / "sparse" / "0")
    first = sparse.images[0]
    clash = PosedImage(first.name.rsplit(".", 1)[0] + ".jpg", first.camera_id, first.cam_from_world)
    cameras = tmp_path / "cameras"
    write_sparse_model(cameras, SparseModel(sparse.cameras, [*sparse.images, clash], sparse.points_xyz,
                                            sparse.points_rgb), binary=False)
    model = tmp_path / "model.ply"
    model.write_bytes(b"ply\n")  # never read: the names are refused first
    monkeypatch.setattr(splat.cli, "read_gaussian_ply", lambda *a, **k: None)
    assert_refused(main, ["render", model, "--cameras", cameras, "--out", tmp_path / "renders"], capsys,
                   inputs=[dataset, model, cameras], watch=[tmp_path], message="two images share the name")


def test_render_refuses_a_camera_it_cannot_render_naming_the_model(dataset, tmp_path, capsys, no_training):
    """A distorted camera is refused before the Gaussians are read, naming the --cameras folder."""
    from mvgeo.camera import Camera
    from mvgeo.sparse_model import SparseModel, read_sparse_model, write_sparse_model

    sparse = read_sparse_model(dataset / "sparse" / "0")
    cam = sparse.cameras[sparse.images[0].camera_id]
    distorted = Camera("OPENCV", cam.width, cam.height, [cam.fx, cam.fy, cam.cx, cam.cy, 0.05, 0.0, 0.0, 0.0])
    cameras = tmp_path / "cameras"
    write_sparse_model(cameras, SparseModel({c: distorted for c in sparse.cameras}, sparse.images,
                                            sparse.points_xyz, sparse.points_rgb), binary=False)
    model = tmp_path / "model.ply"
    model.write_bytes(b"ply\n")  # never read: the camera is refused first
    assert_refused(main, ["render", model, "--cameras", cameras, "--out", tmp_path / "renders"], capsys,
                   inputs=[dataset, model, cameras], watch=[tmp_path],
                   message=[str(cameras), "lens distortion", "fix:"])


@pytest.mark.parametrize("port", ["99999", "-1"])
def test_view_port_out_of_range_is_refused(dataset, tmp_path, capsys, port):
    model = tmp_path / "model.ply"
    model.write_bytes(b"ply\n")
    assert_refused(main, ["view", model, "--port", port], capsys, inputs=[model], watch=[tmp_path],
                   message="argument --port")


def test_view_unknown_host_is_refused_before_loading_and_a_busy_port_is_not(tmp_path, capsys):
    """viser binds in its own thread and retries for ever where binding fails: an unknown host, or an address
    that is not this machine's, left a process waiting with no message. A busy port is viser's to handle (it
    serves on the next free one), so the check accepts it."""
    import socket

    from splat.viewer import check_listen_address

    model = tmp_path / "model.ply"
    model.write_bytes(b"ply\n")  # never read: the address is refused first
    assert_refused(main, ["view", model, "--host", "256.1.1.1"], capsys, inputs=[model], watch=[tmp_path],
                   message=["cannot listen on host '256.1.1.1'", "--host"])
    assert_refused(main, ["view", model, "--host", "192.0.2.1"], capsys, inputs=[model], watch=[tmp_path],
                   message=["cannot listen on host '192.0.2.1'", "--host"])  # TEST-NET-1: never this machine's
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        check_listen_address("127.0.0.1", busy.getsockname()[1])


@pytest.mark.parametrize("case", ["no data folder", "image missing", "bad init", "bad model"])
def test_missing_or_unreadable_inputs_name_the_file_and_the_fix(dataset, tmp_path, capsys, case):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    if case == "image missing":
        for f in (data / "images").iterdir():
            f.unlink()
    argv = {"no data folder": ["train", tmp_path / "nope", "--out", tmp_path / "o"],
            "image missing": ["train", data, "--out", tmp_path / "o", "--init", "depth"],
            "bad init": ["train", data, "--out", tmp_path / "o", "--init", bad],
            "bad model": ["render", bad, "--cameras", data / "sparse" / "0", "--out", tmp_path / "o"]}[case]
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and "fix:" in err, err
    assert not (tmp_path / "o").exists()


_PLY_HEAD = ("ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
             "end_header\n")


@pytest.mark.parametrize(("body", "n", "message"), [("", 0, "holds 0 point(s)"),
                                                    ("0 0 1\nnan 0 1\n1 1 1\n", 3, "1 of its 3 points are NaN")])
def test_an_init_cloud_without_usable_points_is_named_with_a_fix(dataset, tmp_path, capsys, no_training, body, n,
                                                                 message):
    ply = tmp_path / "init.ply"
    ply.write_text(_PLY_HEAD.format(n=n) + body)
    err = assert_refused(main, ["train", str(dataset), "--out", str(tmp_path / "o"), "--init", str(ply)], capsys,
                         inputs=[dataset, ply], watch=[tmp_path], message=[message, "init.ply", "fix:"])
    assert "pass --init" not in err  # they did


def test_an_empty_training_split_names_split_json_and_the_fix(dataset, tmp_path, capsys, no_training):
    import json
    import shutil

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    split = json.loads((data / "split.json").read_text())
    (data / "split.json").write_text(json.dumps({"train": [], "test": split["test"] or split["train"][:1]}))
    assert_refused(main, ["train", str(data), "--out", str(tmp_path / "o"), "--init", "depth"], capsys,
                   inputs=[data], watch=[tmp_path], message=["split.json", "'train' list is empty", "fix:"])
