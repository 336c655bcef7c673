"""`denoise-gs dataset import`: each capture format on a tiny synthetic scene the test writes itself.

Every format test projects the same world points two ways: with the format's own convention, written out
independently here, and with the imported `sparse/0` cameras (our convention); they must agree to 1e-6 px
(float64 throughout; COLMAP text files keep 17 significant digits).
"""

from __future__ import annotations

import json
import logging

import cv2  # before pycolmap, which the importer loads
import numpy as np
import pytest

from eval.cli import main
from eval.pipeline import validate_dataset_folder
from eval.real import import_dataset, parse_noise
from eval.real.split import every_kth_split
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model

# -- a tiny scene ---------------------------------------------------------------------------------


def _look_at(centre: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """(4, 4) cam_from_world, OpenCV axes, camera at `centre` looking at `target`."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, -R @ centre
    return out


def _rig(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """n cam_from_world on an arc 4 units from the origin, looking at it with a little jitter."""
    out = []
    for i in range(n):
        a = np.radians(-30 + 60 * i / max(n - 1, 1))
        centre = np.array([4 * np.sin(a), 0.3 * rng.normal(), -4 * np.cos(a)])
        out.append(_look_at(centre, rng.normal(0, 0.1, 3)))
    return out


def _points(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(-0.8, 0.8, (20, 3))


def _project_ours(model: SparseModel, name: str, X: np.ndarray) -> np.ndarray:
    """Pinhole projection by hand from the imported model (no distortion)."""
    cam, cfw = model.camera_of(name), model.image(name).cam_from_world
    x = X @ cfw[:, :3].T + cfw[:, 3]
    return np.stack([cam.fx * x[:, 0] / x[:, 2] + cam.cx, cam.fy * x[:, 1] / x[:, 2] + cam.cy], axis=1)


def _image(path, w, h, value=None, rng=None):
    img = np.full((h, w, 3), value, np.float32) if value is not None else rng.random((h, w, 3)).astype(np.float32)
    write_image(path, img)


# -- LLFF -----------------------------------------------------------------------------------------


def _llff_row(world_from_cam_llff: np.ndarray, centre: np.ndarray, hwf, near_far) -> np.ndarray:
    return np.r_[np.hstack([world_from_cam_llff, centre[:, None], np.asarray(hwf)[:, None]]).ravel(), near_far]


def _project_llff_nerf(row: np.ndarray, X: np.ndarray, w: int, h: int) -> np.ndarray:
    """Pixels by NeRF's `load_llff_data` path, written out independently of the importer.

    The loader reorders (down, right, back) to OpenGL's (right, up, back): [c1, -c0, c2]. A point in
    that camera frame projects to u = W/2 + f x / (-z), v = H/2 - f y / (-z) (the principal point at the
    image centre, in the convention where the image spans [0, W]); images_N scale all of it by w / W.
    """
    p = row[:15].reshape(3, 5)
    H, W, f = p[:, 4]
    R_gl = np.stack([p[:, 1], -p[:, 0], p[:, 2]], axis=1)  # world_from_cam, OpenGL axes
    x = (X - p[:, 3]) @ R_gl  # = R_gl^T (X - C), row by row
    u = W / 2 + f * x[:, 0] / -x[:, 2]
    v = H / 2 - f * x[:, 1] / -x[:, 2]
    return np.stack([u * w / W, v * h / H], axis=1)


def _write_llff(folder, rng, n=6, W=80, H=60, f=70.0, factor=None):
    folder.mkdir(parents=True)
    rows = []
    for cfw in _rig(n, rng):
        R_wc = cfw[:3, :3].T  # world_from_cam, OpenCV columns (right, down, forward)
        llff_cols = np.stack([R_wc[:, 1], R_wc[:, 0], -R_wc[:, 2]], axis=1)  # (down, right, back)
        rows.append(_llff_row(llff_cols, -R_wc @ cfw[:3, 3], (H, W, f), (2.5, 6.0)))
    arr = np.array(rows)
    np.save(folder / "poses_bounds.npy", arr)
    sub = folder / ("images" if factor is None else f"images_{factor}")
    sub.mkdir(parents=True)
    w, h = (W, H) if factor is None else (round(W / factor), round(H / factor))
    for i in range(n):
        _image(sub / f"IMG_{i:04d}.png", w, h, rng=rng)
    return arr, (w, h)


@pytest.mark.parametrize("factor", [None, 4])
def test_llff_cameras_put_points_where_the_llff_convention_does(tmp_path, rng, factor):
    arr, (w, h) = _write_llff(tmp_path / "llff", rng, factor=factor)
    out = import_dataset("llff", tmp_path / "llff", tmp_path / "ds", test_every=3, llff_factor=factor)
    ds = validate_dataset_folder(out)
    assert ds.test == ["IMG_0000", "IMG_0003"] and ds.train == ["IMG_0001", "IMG_0002", "IMG_0004", "IMG_0005"]
    model = read_sparse_model(out / "sparse" / "0")
    X = _points(rng)
    for name in model.names:
        i = int(name[4:8])
        expect = _project_llff_nerf(arr[i], X, w, h)
        np.testing.assert_allclose(_project_ours(model, name, X), expect, atol=1e-6)
        assert model.camera_of(name).size_wh == (w, h)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["views"]["IMG_0001.png"]["near_far"] == [2.5, 6.0] and meta["noise"] is None


def test_llff_bad_inputs_name_the_file(tmp_path, rng):
    _write_llff(tmp_path / "llff", rng, n=4)
    (tmp_path / "llff" / "poses_bounds.npy").write_text("garbage\n")
    with pytest.raises(InputError, match=r"poses_bounds.npy: not a NumPy .npy file, or a damaged one") as bad:
        import_dataset("llff", tmp_path / "llff", tmp_path / "ds")
    assert "pickle" not in str(bad.value)
    np.savez(tmp_path / "llff" / "pb.npz", a=np.zeros((4, 17)))  # an archive under the array's name
    (tmp_path / "llff" / "pb.npz").replace(tmp_path / "llff" / "poses_bounds.npy")
    with pytest.raises(InputError, match=r"poses_bounds.npy: is an .npz archive, not a single .npy array"):
        import_dataset("llff", tmp_path / "llff", tmp_path / "ds")
    np.save(tmp_path / "llff" / "poses_bounds.npy", np.zeros((4, 15)))
    with pytest.raises(InputError, match=r"poses_bounds.npy.*\(N, 17\).*\(4, 15\)"):
        import_dataset("llff", tmp_path / "llff", tmp_path / "ds")
    arr, _ = _write_llff(tmp_path / "llff2", rng, n=4)
    np.save(tmp_path / "llff2" / "poses_bounds.npy", arr[:3])
    with pytest.raises(InputError, match="3 rows but images/ holds 4 images"):
        import_dataset("llff", tmp_path / "llff2", tmp_path / "ds")
    bad = arr.copy()
    bad[1, 0] = 5.0  # not a rotation
    np.save(tmp_path / "llff2" / "poses_bounds.npy", bad)
    with pytest.raises(InputError, match=r"row 1 \(IMG_0001.png\).*not orthonormal"):
        import_dataset("llff", tmp_path / "llff2", tmp_path / "ds")
    with pytest.raises(InputError, match="images_2"):
        import_dataset("llff", tmp_path / "llff2", tmp_path / "ds", llff_factor=2)
    assert not (tmp_path / "ds").exists()


# -- COLMAP ---------------------------------------------------------------------------------------


def _write_colmap(folder, rng, n=5, binary=True, W=64, H=48, value=None):
    cams = {1: Camera.pinhole(60.0, 62.0, 31.5, 24.25, W, H),
            2: Camera("OPENCV", W, H, [55.0, 55.0, 33.0, 23.0, -0.1, 0.0, 0.0, 0.0])}
    images = [PosedImage(f"sub/im{i}.png", 1 + i % 2, cfw) for i, cfw in enumerate(_rig(n, rng))]
    write_sparse_model(folder / "sparse" / "0", SparseModel(cams, images, rng.normal(size=(7, 3)),
                                                             np.zeros((7, 3), np.uint8)), binary=binary)
    for im in images:
        (folder / "images" / "sub").mkdir(parents=True, exist_ok=True)
        _image(folder / "images" / im.name, W, H, value=value, rng=rng)
    return cams, images


def _project_k1(fx, fy, cx, cy, k1, cfw, X):
    """A pinhole with one radial coefficient, by hand: u = fx x (1 + k1 r^2) + cx."""
    x = X @ cfw[:3, :3].T + cfw[:3, 3]
    a, b = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
    d = 1 + k1 * (a * a + b * b)
    return np.stack([fx * a * d + cx, fy * b * d + cy], axis=1)


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_model_imports_unchanged_and_resizes_exactly(tmp_path, rng, binary):
    cams, images = _write_colmap(tmp_path / "col", rng, binary=binary)
    X = _points(rng)
    out = import_dataset("colmap", tmp_path / "col", tmp_path / "ds", test=1, size_wh=(32, 36))
    model = read_sparse_model(out / "sparse" / "0")
    assert sorted(model.names) == ["sub_im0.png", "sub_im1.png", "sub_im2.png", "sub_im3.png", "sub_im4.png"]
    assert len(model.points_xyz) == 7
    sx, sy = 32 / 64, 36 / 48
    for i, im in enumerate(images):
        got_cam = model.camera_of(f"sub_im{i}.png")
        c = cams[im.camera_id]
        k1 = c.params[4] if c.model == "OPENCV" else 0.0
        expect = _project_k1(c.fx, c.fy, c.cx, c.cy, k1, im.cam_from_world, X) * [sx, sy]
        got = got_cam.project(X @ model.image(f"sub_im{i}.png").R.T + model.image(f"sub_im{i}.png").t).uv_px
        np.testing.assert_allclose(got, expect, atol=1e-6)
        assert read_image(out / "clean" / f"sub_im{i}.png").shape == (36, 32, 3)


def test_colmap_missing_image_is_named(tmp_path, rng):
    _write_colmap(tmp_path / "col", rng)
    (tmp_path / "col" / "images" / "sub" / "im3.png").unlink()
    with pytest.raises(InputError, match=r"image 'sub/im3.png' is missing"):
        import_dataset("colmap", tmp_path / "col", tmp_path / "ds")
    (tmp_path / "col" / "sparse" / "0" / "points3D.bin").unlink()
    with pytest.raises(InputError, match="no complete COLMAP model"):
        import_dataset("colmap", tmp_path / "col", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize("orientation", [3, 6])
def test_photos_with_an_exif_orientation_are_imported_as_stored(tmp_path, orientation):
    """COLMAP ignores the EXIF Orientation tag: its cameras describe the stored pixels, and so must clean/."""
    from PIL import Image

    W, H = 48, 32
    stored = np.zeros((H, W, 3), np.uint8)
    stored[: H // 2, : W // 3] = 255  # a bright block in the stored top-left corner
    (tmp_path / "col" / "images").mkdir(parents=True)
    cams, images = {}, []
    for i in range(3):
        exif = Image.Exif()
        exif[0x0112] = orientation  # 3: turned 180 deg, 6: 90 deg (a phone held upright)
        Image.fromarray(stored).save(tmp_path / "col" / "images" / f"v{i}.jpg", exif=exif, quality=100)
        cams[i + 1] = Camera.pinhole(40.0, 40.0, W / 2, H / 2, W, H)
        cfw = np.eye(4)[:3]
        cfw[0, 3] = 0.1 * i
        images.append(PosedImage(f"v{i}.jpg", i + 1, cfw))
    write_sparse_model(tmp_path / "col" / "sparse" / "0",
                       SparseModel(cams, images, np.zeros((0, 3)), np.zeros((0, 3), np.uint8)), binary=False)
    out = import_dataset("colmap", tmp_path / "col", tmp_path / "ds", test=1)
    clean = read_image(out / "clean" / "v1.png")
    assert clean.shape == (H, W, 3)
    assert clean[: H // 2, : W // 3].mean() > 0.95 and clean[H // 2 :, W // 3 :].mean() < 0.05


# -- Middlebury -----------------------------------------------------------------------------------


def _write_par(folder, rng, n=5, W=64, H=48, value=None):
    """A *_par.txt in Middlebury's convention: K with pixel centres at integer coordinates."""
    folder.mkdir(parents=True)
    K_file = np.array([[70.0, 0.0, 31.2], [0.0, 71.0, 23.7], [0.0, 0.0, 1.0]])
    lines, truth = [str(n)], []
    for i, cfw in enumerate(_rig(n, rng)):
        name = f"tmpl{i:04d}.png"
        lines.append(" ".join([name, *(f"{v:.17g}" for v in (*K_file.ravel(), *cfw[:3, :3].ravel(),
                                                             *cfw[:3, 3]))]))
        truth.append(K_file @ cfw[:3])
        _image(folder / name, W, H, value=value, rng=rng)
    (folder / "tmpl_par.txt").write_text("\n".join(lines) + "\n")
    return truth


def test_middlebury_cameras_match_the_file_projection_plus_half_a_pixel(tmp_path, rng):
    truth = _write_par(tmp_path / "mb", rng)
    out = import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds", test_every=4)
    model = read_sparse_model(out / "sparse" / "0")
    X = _points(rng)
    for name in model.names:
        x = np.hstack([X, np.ones((len(X), 1))]) @ truth[int(name[4:8])].T
        uv_file = x[:, :2] / x[:, 2:]  # file convention: top-left pixel centre at (0, 0)
        np.testing.assert_allclose(_project_ours(model, name, X), uv_file + 0.5, atol=1e-6)
    assert json.loads((out / "split.json").read_text())["test"] == ["tmpl0000.png", "tmpl0004.png"]


def test_middlebury_camera_file_that_is_not_text_is_named(tmp_path, rng):
    _write_par(tmp_path / "mb", rng, n=3)
    (tmp_path / "mb" / "tmpl_par.txt").write_bytes(b"\xff\xfe\x00not text")
    with pytest.raises(InputError, match=r"tmpl_par.txt: cannot read the camera file"):
        import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_middlebury_bad_lines_are_named(tmp_path, rng):
    _write_par(tmp_path / "mb", rng, n=3)
    par = tmp_path / "mb" / "tmpl_par.txt"
    good = par.read_text().splitlines()
    par.write_text("\n".join([good[0], good[1], good[2] + " 7", good[3]]) + "\n")
    with pytest.raises(InputError, match=r"tmpl_par.txt: line 3 has 23 fields, expected 22"):
        import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds")
    par.write_text("\n".join(["4", *good[1:]]) + "\n")
    with pytest.raises(InputError, match="announces 4 views but 3 camera lines follow"):
        import_dataset("middlebury", par, tmp_path / "ds")
    par.write_text("\n".join(good) + "\n")
    (tmp_path / "mb" / "tmpl0001.png").unlink()
    with pytest.raises(InputError, match=r"tmpl0001.png: line 3 names image 'tmpl0001.png', which is missing"):
        import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


# -- splits ---------------------------------------------------------------------------------------


def test_every_kth_split_is_llffs_protocol():
    tr, te = every_kth_split(20, 8)
    assert te == [0, 8, 16] and tr == [i for i in range(20) if i not in te]
    tr3, te3 = every_kth_split(20, 8, 3)
    assert te3 == te and tr3 == [1, 10, 19]  # round(linspace(0, 16, 3)) = 0, 8, 16 of the 17 others
    with pytest.raises(InputError, match="cannot take 18"):
        every_kth_split(20, 8, 18)
    with pytest.raises(InputError, match=">= 2"):
        every_kth_split(20, 1)


def test_spread_split_holds_out_exactly_the_views_asked_for(tmp_path, rng):
    from eval.real.split import spread_split

    for n in range(3, 40):
        for train in range(2, n):
            for test in range(1, n - train + 1):
                tr, te = spread_split(n, train, test)
                assert len(tr) == train and len(te) == test and te == sorted(te) and not set(tr) & set(te)
    assert spread_split(49, 12, 4)[1] == [10, 19, 29, 38]  # midway between training views where that works
    assert spread_split(16, 12, 4)[1] == [2, 6, 9, 13]  # 4 of the 4 others, not 2 of them
    _write_par(tmp_path / "mb", rng, n=8)
    out = import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds", test=4)
    split = json.loads((out / "split.json").read_text())
    assert len(split["train"]) == 4 and len(split["test"]) == 4
    assert len(list((out / "images").iterdir())) == 8


def test_ring_split_keeps_the_ring_closed_whatever_the_file_order():
    from eval.real.split import ring_split

    rng = np.random.default_rng(5)
    angles = np.deg2rad(np.arange(16) * 22.5)  # 16 views 22.5 deg apart ...
    perm = rng.permutation(16)  # ... in a shuffled file order, on a tilted ring, one position repeated
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    centres = np.stack([np.cos(angles), np.sin(angles), np.zeros(16)], axis=1)[perm] @ R.T + [1.0, 2.0, 3.0]
    centres = np.vstack([centres, centres[3]])
    tr, te = ring_split(centres, 12)
    assert len(tr) == 12 and 16 not in te and 16 not in tr  # the repeated position is neither
    assert sorted(tr + te) == list(range(16))
    ring_pos = {int(p): k for k, p in enumerate(perm)}  # file index -> position on the ring
    gaps = np.diff(sorted(ring_pos[v] for v in tr) + [min(ring_pos[v] for v in tr) + 16])
    assert gaps.max() == 2  # 4 views dropped from 16: never two neighbours, so no gap wider than 45 deg
    # a held-out view lies between two training views
    assert all((ring_pos[v] - 1) % 16 in {ring_pos[u] for u in tr} and (ring_pos[v] + 1) % 16 in
               {ring_pos[u] for u in tr} for v in te)
    tr2, te2 = ring_split(centres, 12, test=2)
    assert tr2 == tr and len(te2) == 2 and set(te2) <= set(te)


def test_split_options_that_cannot_work_are_refused_before_writing(tmp_path, rng):
    _write_par(tmp_path / "mb", rng, n=6)
    for kwargs, msg in [({"test": 1, "test_every": 3}, "either --test-every or --test"),
                        ({"views": 6, "test": 1}, "cannot split 6 views"),
                        ({"views": 5, "test_every": 3}, "leave 4 training candidates"),
                        ({"layout": "cluster", "test_every": 3}, "does not apply to the cluster"),
                        ({"layout": "orbit"}, "unknown split layout"),
                        ({"layout": "ring", "test_every": 3}, "does not apply to the ring"),
                        ({"layout": "ring", "views": 6}, "cannot give 6 training views"),
                        ({"seed": -1, "test": 1}, "--seed must be"),
                        ({"size_wh": (4, 4), "test": 1}, "at least 8x8")]:
        with pytest.raises(InputError, match=msg):
            import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds", **kwargs)
    assert not (tmp_path / "ds").exists()


# -- declared noise -------------------------------------------------------------------------------


def test_no_noise_gives_byte_identical_images(tmp_path, rng):
    _write_par(tmp_path / "mb", rng, n=4)
    out = import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds", test=1)
    for f in (out / "clean").iterdir():
        assert f.read_bytes() == (out / "images" / f.name).read_bytes()
    assert json.loads((out / "meta.json").read_text())["noise"] is None


def _diffs(out) -> tuple[np.ndarray, np.ndarray]:
    clean = np.stack([read_image(f) for f in sorted((out / "clean").iterdir())])
    noisy = np.stack([read_image(out / "images" / f.name) for f in sorted((out / "clean").iterdir())])
    return clean, noisy - clean


def test_gaussian_noise_is_what_was_declared(tmp_path, rng):
    _write_par(tmp_path / "mb", rng, n=6, value=0.5)
    out = import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds", test=1, noise="gaussian:25", seed=3)
    _, d = _diffs(out)
    # 6 x 64 x 48 x 3 = 55296 samples: the std's standard error is sigma / sqrt(2N) = 0.3 %, the mean's
    # sigma / sqrt(N) = 4e-4; 8-bit rounding adds variance 1/12 (on 0..255), clipping at 0.5 +- 5 sigma
    # is negligible. Tolerances: about 6 standard errors.
    assert abs(d.std() * 255 - 25.0) < 25.0 * 0.02
    assert abs(d.mean()) < 2.5e-3
    meta = json.loads((out / "meta.json").read_text())["noise"]
    assert meta["model"] == "gaussian" and meta["params"] == {"sigma_8bit": 25.0} and meta["seed"] == 3
    again = import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds2", test=1, noise="gaussian:25", seed=3)
    other = import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds3", test=1, noise="gaussian:25", seed=4)
    f = sorted((out / "images").iterdir())[0].name
    assert (again / "images" / f).read_bytes() == (out / "images" / f).read_bytes()
    assert (other / "images" / f).read_bytes() != (out / "images" / f).read_bytes()


def test_poisson_gaussian_noise_variance_follows_the_signal(tmp_path, rng):
    folder = tmp_path / "mb"
    _write_par(folder, rng, n=6)
    for p in folder.glob("*.png"):  # left half 0.25, right half 0.75
        img = np.full((48, 64, 3), 0.25, np.float32)
        img[:, 32:] = 0.75
        write_image(p, img)
    a, read = 0.01, 5.0
    out = import_dataset("middlebury", folder, tmp_path / "ds", test=1, noise=f"poisson-gaussian:{a},{read}")
    clean, d = _diffs(out)
    for x in (0.25, 0.75):
        sel = np.abs(clean - x) < 1e-3
        expect = a * x + (read / 255) ** 2 + 1 / 12 / 255**2
        # 27648 samples per level: the variance's standard error is sqrt(2/N) = 0.85 %; 5 % is ~6 of them.
        assert abs(d[sel].var() / expect - 1) < 0.05, (x, d[sel].var(), expect)
        assert abs(d[sel].mean()) < 3e-3
    assert json.loads((out / "meta.json").read_text())["noise"]["params"] == {"gain": a, "read_sigma_8bit": read}


def test_noise_then_jpeg_compresses_exactly_the_noise_alone_draws(tmp_path, rng):
    _write_par(tmp_path / "mb", rng, n=4)
    alone = import_dataset("middlebury", tmp_path / "mb", tmp_path / "a", test=1, noise="gaussian:25", seed=2)
    chain = import_dataset("middlebury", tmp_path / "mb", tmp_path / "b", test=1, noise="gaussian:25+jpeg:90", seed=2)
    for f in sorted((alone / "images").iterdir()):
        bgr = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        assert bgr.dtype == np.uint8  # 8-bit files: the JPEG step encodes exactly these values
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
        expect = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        got = cv2.imread(str(chain / "images" / f.name), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(got, expect)
        assert np.abs(got.astype(int) - bgr).max() > 0  # the compression changed the noisy photo
    meta = json.loads((chain / "meta.json").read_text())["noise"]
    assert [s["model"] for s in meta["steps"]] == ["gaussian", "jpeg"] and meta["steps"][1]["params"] == {"quality": 90}
    assert "model" not in meta and meta["spec"] == "gaussian:25+jpeg:90"


def test_parse_noise_rejects_what_it_does_not_know():
    assert parse_noise(None).is_none and parse_noise("none").is_none
    assert parse_noise("Gaussian: 10").params == {"sigma_8bit": 10.0}
    assert parse_noise("bayer-pg:0.01,5").effect == "bayer_noise"
    chain = parse_noise("bayer-pg:0.01,5 + JPEG:90")
    assert [s.effect for s in chain.steps] == ["bayer_noise", "jpeg"] and chain.steps[1].params == {"quality": 90}
    for bad, msg in [("gauss:3", "unknown noise model"), ("gaussian:", "expected 1 number"),
                     ("gaussian:1,2", "expected 1 number"), ("poisson-gaussian:0.1", "expected 2 numbers"),
                     ("bayer-pg:0.01", "expected 2 numbers"), ("bayer-pg:0,5", "out of range"),
                     ("gaussian:-3", "out of range"), ("jpeg:0", "out of range"), ("jpeg:90.5", "whole number"),
                     ("gaussian:25+", "empty step"), ("jpeg:90+gaussian:5+jpeg:80", "same step twice")]:
        with pytest.raises(InputError, match=msg):
            parse_noise(bad)


# -- output policy and command line ---------------------------------------------------------------


def test_out_holding_other_files_is_refused_and_left_alone(tmp_path, rng):
    _write_par(tmp_path / "mb", rng, n=4)
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "precious.txt").write_text("x")
    with pytest.raises(InputError, match="did not write"):
        import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds", test=1)
    assert [p.name for p in (tmp_path / "ds").iterdir()] == ["precious.txt"]
    out = import_dataset("middlebury", tmp_path / "mb", tmp_path / "ds2", test=1)
    with pytest.raises(InputError, match="previous output"):
        import_dataset("middlebury", tmp_path / "mb", out, test=1, noise="gaussian:5")
    import_dataset("middlebury", tmp_path / "mb", out, test=1, noise="gaussian:5", overwrite=True)
    assert json.loads((out / "meta.json").read_text())["noise"]["params"] == {"sigma_8bit": 5.0}


@pytest.fixture
def _keep_logging():
    """The CLI points the root logger at the captured stderr; put the handlers back afterwards."""
    root = logging.getLogger()
    saved = root.handlers[:]
    yield
    root.handlers[:] = saved


def test_cli_imports_and_bad_input_exits_2_without_traceback(tmp_path, rng, capsys, _keep_logging):
    _write_par(tmp_path / "mb", rng, n=5)
    assert main(["dataset", "import", "middlebury", str(tmp_path / "mb"), "--out", str(tmp_path / "ds"),
                 "--views", "3", "--test", "1", "--noise", "gaussian:10", "--max-size", "32"]) == 0
    ds = validate_dataset_folder(tmp_path / "ds")
    assert len(ds.train) == 3 and len(ds.test) == 1
    assert read_image(tmp_path / "ds" / "images" / f"{ds.train[0]}.png").shape == (24, 32, 3)
    capsys.readouterr()
    par = tmp_path / "mb" / "tmpl_par.txt"
    lines = par.read_text().splitlines()
    par.write_text("\n".join([lines[0], *lines[1:-1], lines[-1].rsplit(" ", 1)[0]]) + "\n")
    good_poses, _ = _write_llff(tmp_path / "llff", rng, n=3)
    np.save(tmp_path / "llff" / "poses_bounds.npy", np.zeros((3, 3, 5)))
    cases = [(["middlebury", str(tmp_path / "mb")], "line 6 has 21 fields"),
             (["llff", str(tmp_path / "llff")], "poses_bounds.npy must be an (N, 17)"),
             (["dtu", str(tmp_path / "mb")], "not a DTU scan folder"),
             (["colmap", str(tmp_path / "nope")], "does not exist")]
    for args, msg in cases:
        assert main(["dataset", "import", *args, "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err and "fix:" in err, err
        assert not (tmp_path / "bad").exists()
    bad_par = [("", "the camera file is empty"), ("five\n", "the first line must be the number of views"),
               (lines[0] + "\n" + lines[1].replace(lines[1].split()[1], "x", 1) + "\n", "not a number")]
    for text, msg in bad_par:  # each names the file and says how the file is laid out
        par.write_text(text if msg != "not a number" else "1\n" + text.split("\n", 1)[1])
        assert main(["dataset", "import", "middlebury", str(par), "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert msg in err and "tmpl_par.txt" in err and "fix: write it as Middlebury's" in err, err
    np.save(tmp_path / "llff" / "poses_bounds.npy", good_poses)
    assert main(["dataset", "import", "llff", str(tmp_path / "llff"), "--out", str(tmp_path / "bad"),
                 "--factor", "2"]) == 2
    err = capsys.readouterr().err
    assert "--factor 2 reads images_2/" in err and "leave --factor out" in err, err
    assert main(["dataset", "import", "middlebury", str(tmp_path / "mb"), "--out", str(tmp_path / "bad"),
                 "--factor", "2"]) == 2
    assert "fix: leave --factor out" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    assert main(["dataset", "import", "llff", str(tmp_path / "llff"), "--out", str(tmp_path / "bad"),
                 "--noise", "speckle:3"]) == 2
    assert "unknown noise model" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:  # a size no image may have, refused before any image is read
        main(["dataset", "import", "llff", str(tmp_path / "llff"), "--out", str(tmp_path / "bad"),
              "--size", "100000x100000"])
    assert info.value.code == 2 and "8..8192" in capsys.readouterr().err and not (tmp_path / "bad").exists()


# -- camera check (eval.real.check) ---------------------------------------------------------------


def _plane_dataset(folder, rng, cams, W=160, H=120):
    """Views of a textured plane z = 0 ([-1, 1]^2), rendered exactly through homographies."""
    from mvgeo.common.deps import cv2

    S = 256
    tex = cv2.GaussianBlur(rng.random((S, S, 3)).astype(np.float32), (0, 0), 1.5)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    A = np.array([[2 / S, 0, -1], [0, 2 / S, -1], [0, 0, 1]])  # texture pixels (ours) -> plane (X, Y, 1)
    half = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])  # OpenCV pixel centres -> ours
    K = np.array([[150.0, 0, W / 2], [0, 150.0, H / 2], [0, 0, 1]])
    images = []
    for i, cfw in enumerate(cams):
        H_ours = K @ cfw[:3][:, [0, 1, 3]] @ A
        H_cv = np.linalg.inv(half) @ H_ours @ half
        write_image(folder / "clean" / f"v{i}.png", cv2.warpPerspective(tex, H_cv, (W, H), flags=cv2.INTER_CUBIC))
        images.append(PosedImage(f"v{i}.png", 1, cfw))
    write_sparse_model(folder / "sparse" / "0", SparseModel({1: Camera.from_K(K, W, H)}, images), binary=False)


def test_camera_check_transfer_error_is_small_with_true_cameras(tmp_path, rng):
    from eval.real.check import box_coverage, transfer_error

    cams = [_look_at(np.array([0.6 * np.sin(a), 0.2 * np.cos(a), -2.5]), np.zeros(3))
            for a in np.radians([0, 72, 144, 216, 288])]
    _plane_dataset(tmp_path, rng, cams)
    right, shifted = transfer_error(tmp_path, offsets_px=(0.0, 3.0))
    # Exact renders: SIFT localisation on 160x120 views is the only error (measured median 0.07 px);
    # a 3 px principal-point error in every view, with views 0.1-0.25 rad apart, is only partly absorbed
    # by moving the points (measured 0.21 px).
    assert right.n_transfers > 50 and right.median_px < 0.15, right
    assert shifted.median_px > right.median_px + 0.1, (right, shifted)
    cov = box_coverage(tmp_path, (-1, -1, -0.01), (1, 1, 0.01), threshold=0.0, chroma_threshold=-1.0)
    off = box_coverage(tmp_path, (-1, -1, -0.01), (0, 0, 0.01), threshold=0.0, chroma_threshold=-1.0)
    # The plane covers about 3/4 of each view; all of it lies inside its own box, a quarter of it in a quarter box.
    assert min(cov.values()) > 0.99 and max(off.values()) < 0.35, (cov, off)


# -- impossible cameras ----------------------------------------------------------------------------


def test_colmap_camera_with_zero_focal_is_refused(tmp_path, rng):
    _write_colmap(tmp_path / "col", rng)
    model = read_sparse_model(tmp_path / "col" / "sparse" / "0")
    cams = dict(model.cameras)
    cams[1] = Camera.pinhole(0.0, 0.0, 32.0, 24.0, 64, 48)
    write_sparse_model(tmp_path / "col" / "sparse" / "0", SparseModel(cams, model.images, model.points_xyz,
                                                                      model.points_rgb), binary=True)
    with pytest.raises(InputError, match=r"focal length 0 x 0 px; it must be positive") as err:
        import_dataset("colmap", tmp_path / "col", tmp_path / "ds")
    assert "cameras.txt / cameras.bin" in str(err.value)
    assert not (tmp_path / "ds").exists()


def _write_dtu(folder, rng, n=3):
    """A DTU scan folder at MonoSDF's 384x384: world_mat_i = K [R | t] at 1600x1200, scale_mat_i = I."""
    (folder / "images").mkdir(parents=True)
    K = np.array([[2892.3, 0.0, 823.2], [0.0, 2883.2, 619.1], [0.0, 0.0, 1.0]])
    mats = {}
    for i, cfw in enumerate(_rig(n, rng)):
        world = np.eye(4)
        world[:3] = K @ cfw[:3]
        mats[f"world_mat_{i}"], mats[f"scale_mat_{i}"] = world, np.eye(4)
        _image(folder / "images" / f"{i:06d}.png", 384, 384, value=0.5)
    np.savez(folder / "cameras.npz", **mats)
    return mats


def test_dtu_singular_projection_is_refused_with_exit_2(tmp_path, rng, capsys, _keep_logging):
    mats = _write_dtu(tmp_path / "dtu", rng)
    assert len(import_dataset("dtu", tmp_path / "dtu", tmp_path / "ok", test=1).name) > 0
    mats["world_mat_1"] = np.zeros((4, 4))
    np.savez(tmp_path / "dtu" / "cameras.npz", **mats)
    capsys.readouterr()
    assert main(["dataset", "import", "dtu", str(tmp_path / "dtu"), "--out", str(tmp_path / "bad"),
                 "--test", "1"]) == 2
    err = capsys.readouterr().err
    assert "view 1: world_mat_1 @ scale_mat_1 is not a camera projection" in err and "cameras.npz" in err, err
    assert "Traceback" not in err and "RuntimeWarning" not in err, err
    assert not (tmp_path / "bad").exists()
    mats["world_mat_1"] = np.full((4, 4), np.nan)
    np.savez(tmp_path / "dtu" / "cameras.npz", **mats)
    assert main(["dataset", "import", "dtu", str(tmp_path / "dtu"), "--out", str(tmp_path / "bad"),
                 "--test", "1"]) == 2
    err = capsys.readouterr().err
    assert "view 1: world_mat_1 @ scale_mat_1 is not a camera projection" in err, err
    assert "Traceback" not in err and "Warning" not in err, err
    assert not (tmp_path / "bad").exists()


def test_dtu_cameras_follow_the_image_numbers_not_their_order(tmp_path, rng):
    """An images folder with a gap: each view keeps its own camera (by the number in its name), not the
    camera of its position in sorted order, which would shift every view after the gap."""
    from eval.real.dtu import read_dtu

    _write_dtu(tmp_path / "dtu", rng, n=4)
    full = {v.name: v.cam_from_world for v in read_dtu(tmp_path / "dtu").views}
    (tmp_path / "dtu" / "images" / "000001.png").unlink()
    gap = read_dtu(tmp_path / "dtu")
    assert [v.name for v in gap.views] == ["000000", "000002", "000003"]
    for v in gap.views:
        np.testing.assert_allclose(v.cam_from_world, full[v.name], atol=1e-9)
    # Names that are not numbers: positions, and then exactly one camera per image.
    for k, f in enumerate(sorted((tmp_path / "dtu" / "images").glob("*.png"))):
        f.rename(f.with_name(f"view_{'abc'[k]}.png"))
    with pytest.raises(InputError, match="3 images, 4 cameras, and the images' names are not all camera numbers"):
        read_dtu(tmp_path / "dtu")
    # Numbers that are not camera indices (a folder numbered from 1), one camera per image: by position.
    # IDR-style files also hold world_mat_inv_i, which are not cameras.
    mats = {k: v for k, v in np.load(tmp_path / "dtu" / "cameras.npz").items() if not k.endswith("_3")}
    mats.update({f"world_mat_inv_{i}": np.linalg.inv(mats[f"world_mat_{i}"]) for i in range(3)})
    np.savez(tmp_path / "dtu" / "cameras.npz", **mats)
    for k, f in enumerate(sorted((tmp_path / "dtu" / "images").glob("*.png"))):
        f.rename(f.with_name(f"{k + 1:04d}.png"))
    by_position = read_dtu(tmp_path / "dtu").views
    for k, v in enumerate(by_position):  # the k-th image takes world_mat_k
        np.testing.assert_allclose(v.cam_from_world, full[f"{k:06d}"], atol=1e-9)


def test_dtu_cameras_file_that_is_not_an_archive_is_named(tmp_path, rng, capsys, _keep_logging):
    _write_dtu(tmp_path / "dtu", rng)
    (tmp_path / "dtu" / "cameras.npz").write_text("garbage\n")
    capsys.readouterr()
    assert main(["dataset", "import", "dtu", str(tmp_path / "dtu"), "--out", str(tmp_path / "bad"),
                 "--test", "1"]) == 2
    err = capsys.readouterr().err
    assert "cameras.npz: not a NumPy .npz archive, or a damaged one" in err, err
    assert "pickle" not in err and "Traceback" not in err, err
    assert not (tmp_path / "bad").exists()
    np.save(tmp_path / "dtu" / "cameras.npy", np.eye(4))  # one array saved under the archive's name
    (tmp_path / "dtu" / "cameras.npy").rename(tmp_path / "dtu" / "cameras.npz")
    assert main(["dataset", "import", "dtu", str(tmp_path / "dtu"), "--out", str(tmp_path / "bad"),
                 "--test", "1"]) == 2
    err = capsys.readouterr().err
    assert "cameras.npz: holds a single array, not an .npz archive" in err and "Traceback" not in err, err
    assert not (tmp_path / "bad").exists()


def test_dtu_camera_with_skew_is_refused_not_dropped(tmp_path, rng):
    """A pinhole camera holds no skew; dropping it would move pixels at the edge by |skew| 600 / fy."""
    mats = _write_dtu(tmp_path / "dtu", rng)
    K_skew = np.array([[2892.3, 2.0, 823.2], [0.0, 2883.2, 619.1], [0.0, 0.0, 1.0]])  # 0.42 px at the edge
    K = np.array([[2892.3, 0.0, 823.2], [0.0, 2883.2, 619.1], [0.0, 0.0, 1.0]])
    original = mats["world_mat_2"][:3].copy()
    mats["world_mat_2"][:3] = K_skew @ np.linalg.inv(K) @ original
    np.savez(tmp_path / "dtu" / "cameras.npz", **mats)
    with pytest.raises(InputError, match=r"view 2: the camera has skew \(2: 0.42 px"):
        import_dataset("dtu", tmp_path / "dtu", tmp_path / "ds", test=1)
    assert not (tmp_path / "ds").exists()
    K_small = np.array([[2892.3, 0.1, 823.2], [0.0, 2883.2, 619.1], [0.0, 0.0, 1.0]])  # 0.02 px: kept
    mats["world_mat_2"][:3] = K_small @ np.linalg.inv(K) @ original
    np.savez(tmp_path / "dtu" / "cameras.npz", **mats)
    assert import_dataset("dtu", tmp_path / "dtu", tmp_path / "ds", test=1).is_dir()
