"""COLMAP model I/O round trips through pycolmap, in text and binary."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvgeo.camera import Camera
from mvgeo.common import InputError
from mvgeo.common.deps import pycolmap
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model


def _random_model(rng, n=5, n_points=7):
    cams = {1: Camera.pinhole(500.0, 490.0, 320.5, 240.5, 640, 480),
            2: Camera("OPENCV", 320, 240, [250.0, 251.0, 160.0, 120.0, 0.01, -0.002, 1e-4, -2e-4])}
    images = []
    for i in range(n):
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        t = rng.normal(size=3)
        images.append(PosedImage(f"{i:03d}.png", 1 + i % 2, np.hstack([R, t[:, None]])))
    xyz = rng.normal(size=(n_points, 3))
    rgb = rng.integers(0, 256, size=(n_points, 3)).astype(np.uint8)
    return SparseModel(cams, images[::-1], xyz, rgb)


@pytest.mark.parametrize("binary", [False, True])
def test_roundtrip(tmp_path, rng, binary):
    model = _random_model(rng)
    write_sparse_model(tmp_path, model, binary=binary)
    back = read_sparse_model(tmp_path)
    assert back.names == sorted(model.names)
    for im in model.images:
        # text files store poses with 17 significant digits; binary exactly (float64)
        np.testing.assert_allclose(back.image(im.name).cam_from_world, im.cam_from_world, atol=1e-12)
        got, want = back.camera_of(im.name), model.camera_of(im.name)
        assert got.model == want.model and got.size_wh == want.size_wh
        np.testing.assert_allclose(got.params, want.params, rtol=1e-14)
    order = np.lexsort(model.points_xyz.T)
    order_b = np.lexsort(back.points_xyz.T)
    np.testing.assert_allclose(back.points_xyz[order_b], model.points_xyz[order], atol=1e-12)
    np.testing.assert_array_equal(back.points_rgb[order_b], model.points_rgb[order])


def test_pose_and_quaternion_agree_with_pycolmap(tmp_path, rng):
    """Our (3,4) cam_from_world equals pycolmap's, and the file stores wxyz."""
    model = _random_model(rng, n=1, n_points=0)
    write_sparse_model(tmp_path, model, binary=False)
    rec = pycolmap.Reconstruction(str(tmp_path))
    (image,) = rec.images.values()
    np.testing.assert_allclose(image.cam_from_world().matrix(), model.images[0].cam_from_world, atol=1e-12)
    line = [ln for ln in (tmp_path / "images.txt").read_text().splitlines() if ln and not ln.startswith("#")][0]
    qw, qx, qy, qz = map(float, line.split()[1:5])
    R = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
    np.testing.assert_allclose(R, model.images[0].R, atol=1e-12)


def test_centre_world(rng):
    R = Rotation.random(random_state=1).as_matrix()
    C = np.array([1.0, -2.0, 3.0])
    im = PosedImage("a.png", 1, np.hstack([R, (-R @ C)[:, None]]))
    np.testing.assert_allclose(im.centre_world, C, atol=1e-12)


def test_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_sparse_model(tmp_path / "missing")
    with pytest.raises(InputError, match="no complete COLMAP model"):
        read_sparse_model(tmp_path)
    with pytest.raises(InputError, match="unknown camera model"):
        Camera("FISHEYE_XYZ", 10, 10, [1.0])
    with pytest.raises(InputError, match="takes 4 parameters"):
        Camera("PINHOLE", 10, 10, [1.0, 2.0])
    with pytest.raises(InputError, match="missing camera"):
        SparseModel({}, [PosedImage("a.png", 3, np.eye(4))])


def _image_lines(path):
    lines = (path / "images.txt").read_text().split("\n")
    return lines, [k for k, ln in enumerate(lines) if ln and not ln.startswith("#")]


def test_a_text_model_missing_a_line_is_refused_not_read_short(tmp_path, rng):
    # pycolmap takes the line after an image line as its points whatever it holds: with an empty POINTS2D line
    # gone, the next image's line is read as points and that image vanishes without an error.
    model = _random_model(rng, n=4)
    write_sparse_model(tmp_path / "m", model, binary=False)
    lines, data = _image_lines(tmp_path / "m")
    assert len(data) == 4 and lines[data[0] + 1] == ""  # COLMAP's layout: image line, then an empty points line
    assert len(read_sparse_model(tmp_path / "m").images) == 4

    spaced = lines[:data[1]] + ["", ""] + lines[data[1]:]  # blank lines before an image line: COLMAP skips them
    (tmp_path / "m" / "images.txt").write_text("\n".join(spaced))
    assert len(read_sparse_model(tmp_path / "m").images) == 4

    del lines[data[1] + 1]  # the second image's (empty) points line
    (tmp_path / "m" / "images.txt").write_text("\n".join(lines))
    with pytest.raises(InputError, match="POINTS2D line of image") as exc:
        read_sparse_model(tmp_path / "m")
    assert exc.value.path.name == "images.txt" and exc.value.fix


def test_a_text_model_whose_header_count_disagrees_is_refused(tmp_path, rng):
    write_sparse_model(tmp_path / "m", _random_model(rng, n=4), binary=False)
    lines, data = _image_lines(tmp_path / "m")
    del lines[data[-1]:data[-1] + 2]  # the last image, both its lines: the file is sound but one short
    (tmp_path / "m" / "images.txt").write_text("\n".join(lines))
    with pytest.raises(InputError, match="header says 4 image"):
        read_sparse_model(tmp_path / "m")
    header = [k for k, ln in enumerate(lines) if ln.startswith("# Number of images")]
    assert len(header) == 1
    lines[header[0]] = "# a hand-written model without the count"
    (tmp_path / "m" / "images.txt").write_text("\n".join(lines))
    assert len(read_sparse_model(tmp_path / "m").images) == 3
