"""`denoise` CLI: outputs, 16-bit/gray files, selection JSON, and exit code 2 on bad input."""

import json

import numpy as np
import pytest
import torch

from denoise.cli import main
from denoise.model import load_checkpoint, save_checkpoint
from denoise.n2v import N2VConfig, new_model
from denoise.unet import UNetConfig
from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model
from tests.denoise._synth import add_noise, smooth_scene
from tests.denoise.test_view_selection import _ring_poses


def _three_photos(src, rng):
    """A folder of noisy photos: 8-bit colour `a.png`, 16-bit colour `b16.png`, 8-bit gray `c_gray.png`."""
    src.mkdir()
    write_image(src / "a.png", add_noise(rng, smooth_scene(rng, 40, 44), 0.1))
    write_image(src / "b16.png", add_noise(rng, smooth_scene(rng, 40, 44), 0.1), bits=16)
    gray = (add_noise(rng, smooth_scene(rng, 36, 30), 0.1)[..., 0] * 255).round().astype(np.uint8)
    cv2.imwrite(str(src / "c_gray.png"), gray)
    return src


def test_n2v_cli_writes_outputs(tmp_path, rng):
    src = _three_photos(tmp_path / "noisy", rng)
    out = tmp_path / "out"
    rc = main(["n2v", str(src), "--out", str(out), "--steps", "3", "--passes", "2", "--preset", "fast",
               "--noise-model", "curve"])
    assert rc == 0
    assert sorted(p.name for p in (out / "images").iterdir()) == ["a.png", "b16.png", "c_gray.png"]
    assert cv2.imread(str(out / "images" / "b16.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    assert cv2.imread(str(out / "images" / "c_gray.png"), cv2.IMREAD_UNCHANGED).shape == (36, 30)  # still gray
    sheet = read_image(out / "contact_sheet.png")
    assert sheet.shape[0] == 3 * (160 + 4)
    model = load_checkpoint(out / "model.pt")
    assert len(model.history) == 3
    report = json.loads((out / "report.json").read_text())
    assert report["steps"] == 3 and report["passes"] == 2 and report["noise_model"] == "curve"
    assert not list(tmp_path.glob(".out.tmp-*"))


def test_n2v_cli_wiener_refines_colour_16_bit_and_gray_photos(tmp_path, rng):
    # --wiener with R2R and a per-pixel noise map (the curve model): colour, 16-bit and gray photos come out in
    # their formats, and differ from the same run without the step.
    src = _three_photos(tmp_path / "noisy", rng)
    args = ["--steps", "3", "--passes", "1", "--preset", "fast", "--method", "r2r", "--noise-model", "curve"]
    assert main(["n2v", str(src), "--out", str(tmp_path / "plain"), *args]) == 0
    assert main(["n2v", str(src), "--out", str(tmp_path / "w"), *args, "--wiener"]) == 0
    assert json.loads((tmp_path / "w" / "report.json").read_text())["wiener"] is True
    for name in ("a.png", "b16.png", "c_gray.png"):
        a = cv2.imread(str(tmp_path / "plain" / "images" / name), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(tmp_path / "w" / "images" / name), cv2.IMREAD_UNCHANGED)
        assert a.shape == b.shape and a.dtype == b.dtype
        assert np.abs(a.astype(np.float64) - b).max() > 0


def test_n2v_cli_grouped_wiener_passes(tmp_path, rng):
    # --grouped-wiener-passes 2 turns the grouped step on and runs it twice: the photos differ from one pass,
    # and the report says what ran (without the step, no passes).
    src = _three_photos(tmp_path / "noisy", rng)
    args = ["--steps", "3", "--passes", "1", "--preset", "fast", "--method", "r2r", "--seed", "1"]
    assert main(["n2v", str(src), "--out", str(tmp_path / "one"), *args, "--grouped-wiener"]) == 0
    assert main(["n2v", str(src), "--out", str(tmp_path / "two"), *args, "--grouped-wiener-passes", "2"]) == 0
    assert main(["n2v", str(src), "--out", str(tmp_path / "none"), *args]) == 0
    reports = {k: json.loads((tmp_path / k / "report.json").read_text()) for k in ("one", "two", "none")}
    assert [(r["grouped_wiener"], r["grouped_wiener_passes"]) for r in reports.values()] == [
        (True, 1), (True, 2), (False, 0)]
    a = cv2.imread(str(tmp_path / "one" / "images" / "a.png"), cv2.IMREAD_UNCHANGED)
    b = cv2.imread(str(tmp_path / "two" / "images" / "a.png"), cv2.IMREAD_UNCHANGED)
    assert np.abs(a.astype(np.float64) - b).max() > 0


def test_n2v_cli_input_errors(tmp_path, capsys):
    assert main(["n2v", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "x.png").write_bytes(b"not a png")
    assert main(["n2v", str(tmp_path / "bad"), "--out", str(tmp_path / "o")]) == 2
    assert "x.png" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # no half-written output


def test_checkpoint_roundtrip_and_corrupt(tmp_path):
    model = new_model(N2VConfig(unet=UNetConfig(width=4, blurpool=True, top_skip=False), replacement="median",
                                radius=2), [torch.rand(3, 8, 8)], seed=1)
    save_checkpoint(tmp_path / "m.pt", model)
    back = load_checkpoint(tmp_path / "m.pt")
    x = torch.rand(1, 3, 12, 12)
    with torch.no_grad():
        torch.testing.assert_close(back.apply(x), model.apply(x), rtol=0, atol=0)
    assert back.unet_config == model.unet_config and back.mean == model.mean
    assert (back.replacement, back.radius, back.mask_prob) == (model.replacement, model.radius, model.mask_prob)
    (tmp_path / "bad.pt").write_bytes(b"garbage")
    with pytest.raises(InputError, match="bad.pt"):
        load_checkpoint(tmp_path / "bad.pt")
    with pytest.raises(InputError):
        load_checkpoint(tmp_path / "none.pt")


def test_select_cli(tmp_path, rng, capsys):
    poses = _ring_poses(6)
    cams = {1: Camera("PINHOLE", 32, 32, [30.0, 30.0, 16.0, 16.0])}
    images = [PosedImage(f"{i:02d}.png", 1, P) for i, P in enumerate(poses)]
    sparse = tmp_path / "sparse" / "0"
    write_sparse_model(sparse, SparseModel(cameras=cams, images=images), binary=False)
    img_dir = tmp_path / "images"
    for i in range(6):
        write_image(img_dir / f"{i:02d}.png", rng.random((32, 32, 3)))
    out_json = tmp_path / "sel.json"
    assert main(["select", str(sparse), "--images", str(img_dir), "--k", "3", "--out", str(out_json)]) == 0
    data = json.loads(out_json.read_text())
    assert len(data["selected"]) == 3 and set(data["views"]) == {f"{i:02d}.png" for i in range(6)}
    assert json.loads(capsys.readouterr().out) == data
    # A missing image file is an input error naming it.
    (img_dir / "03.png").unlink()
    assert main(["select", str(sparse), "--images", str(img_dir)]) == 2
    assert "03.png" in capsys.readouterr().err
    # An image of another size than its camera: refused, naming both sizes (its sharpness would be measured on
    # other pixels than the model's).
    write_image(img_dir / "03.png", rng.random((24, 32, 3)))
    assert main(["select", str(sparse), "--images", str(img_dir)]) == 2
    err = capsys.readouterr().err
    assert "03.png" in err and "32x24" in err and "32x32" in err and "fix:" in err


def test_n2v_cli_auto_method_chooses_from_the_photos(tmp_path):
    rng = np.random.default_rng(3)
    src = tmp_path / "noisy"
    src.mkdir()
    for k in range(2):
        clean = np.full((40, 48, 3), 0.6)
        clean[:, :30] = 0.0  # a black background over most of the photo
        write_image(src / f"v{k}.png", np.clip(clean + 0.1 * rng.standard_normal(clean.shape), 0, 1))
    out = tmp_path / "out"
    assert main(["n2v", str(src), "--out", str(out), "--steps", "3", "--passes", "1", "--preset", "fast",
                 "--method", "auto"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["method"] == "neighbor2neighbor" and report["objective_rule"] == "auto"
    assert report["dark_clipped_fraction"] > 0.5


def test_n2v_cli_pixel_shuffle_keeps_shapes_and_records_the_stride(tmp_path, rng, capsys):
    # Colour, 16-bit and gray photos through stride 2: each comes back whole, in its own format. With the
    # stride measured (0), white noise gets none.
    src = _three_photos(tmp_path / "noisy", rng)
    out = tmp_path / "out"
    assert main(["n2v", str(src), "--out", str(out), "--steps", "2", "--passes", "1", "--preset", "fast",
                 "--pd-stride", "2"]) == 0
    assert cv2.imread(str(out / "images" / "a.png")).shape == (40, 44, 3)
    assert cv2.imread(str(out / "images" / "c_gray.png"), cv2.IMREAD_UNCHANGED).shape == (36, 30)
    assert json.loads((out / "report.json").read_text())["pd_stride"] == 2
    # With the objective chosen from the photos the report keeps both records.
    assert main(["n2v", str(src), "--out", str(tmp_path / "out_auto"), "--steps", "2", "--passes", "1",
                 "--preset", "fast", "--pd-stride", "2", "--method", "auto"]) == 0
    report = json.loads((tmp_path / "out_auto" / "report.json").read_text())
    assert report["pd_stride"] == 2 and report["objective_rule"] == "auto" and "dark_clipped_fraction" in report
    assert main(["n2v", str(src), "--out", str(tmp_path / "auto"), "--steps", "2", "--passes", "1",
                 "--preset", "fast"]) == 0
    report = json.loads((tmp_path / "auto" / "report.json").read_text())
    assert report["pd_stride"] == 1  # photos this small are not measured: no stride
    tiny = tmp_path / "tiny"
    tiny.mkdir()
    write_image(tiny / "t.png", add_noise(rng, smooth_scene(rng, 7, 9), 0.1))
    assert main(["n2v", str(tiny), "--out", str(tmp_path / "t_out"), "--steps", "2", "--pd-stride", "4"]) == 2
    err = capsys.readouterr().err
    assert "t.png" in err and "--pd-stride" in err and not (tmp_path / "t_out").exists()
