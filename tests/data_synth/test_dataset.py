"""The dataset folder: layout, bit identity without effects, determinism, stream independence."""

from __future__ import annotations

import hashlib
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from data_synth import load_scene, parse_scene, render_scene
from data_synth.scene_file import scene_to_toml
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image
from mvgeo.common.output import MANIFEST_NAME
from mvgeo.sparse_model import read_sparse_model
from tests.data_synth.conftest import TINY_SCENE, write_scene

NOISY = TINY_SCENE.replace('[scene]\nname = "tiny"', '[scene]\nname = "tiny_noisy"') + """
[[effects]]
type = "gaussian"
sigma_8bit = 20.0

[[effects]]
type = "vignetting"
strength = 0.2
"""


def _digest(folder: Path) -> dict[str, str]:
    """sha256 of every data file; meta.json (timings) and the output manifest (creation time) excluded."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name not in ("meta.json", MANIFEST_NAME)}


def test_layout_and_contents(tiny_scene_file, tmp_path):
    out = render_scene(tiny_scene_file, tmp_path / "ds")
    names = ["view_000", "view_001", "view_002"]
    for sub, suffix in (("images", ".png"), ("clean", ".png"), ("depth", ".npy"), ("alpha", ".npy"),
                        ("normals", ".npy")):
        assert sorted(p.name for p in (out / sub).iterdir()) == [n + suffix for n in names]
    # pycolmap 4 also writes rigs.txt and frames.txt (trivial rigs); COLMAP reads both layouts.
    assert {"cameras.txt", "images.txt", "points3D.txt"} <= {p.name for p in (out / "sparse" / "0").iterdir()}
    points = (out / "sparse" / "0" / "points3D.txt").read_text().splitlines()
    assert [ln for ln in points if ln.strip() and not ln.startswith("#")] == []  # empty point cloud
    depth = np.load(out / "depth" / "view_000.npy")
    assert depth.dtype == np.float32 and depth.shape == (48, 64)
    assert read_image(out / "clean" / "view_000.png").shape == (48, 64, 3)
    split = json.loads((out / "split.json").read_text())
    assert split == {"train": ["view_001.png", "view_002.png"], "test": ["view_000.png"]}  # every 8th from 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["views"] == 3 and meta["seed"] == 3 and meta["timings_s"]["total"] > 0
    model = read_sparse_model(out / "sparse" / "0")
    assert [im.name for im in model.images] == [n + ".png" for n in names]
    # The written scene.toml is the resolved spec: it parses back to the same scene.
    back = parse_scene(tomllib.loads((out / "scene.toml").read_text()))
    spec = load_scene(tiny_scene_file)
    assert back.__class__ is spec.__class__
    assert scene_to_toml(back) == scene_to_toml(spec)
    # No temporary folders left beside the output.
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_no_effects_means_images_identical_to_clean(tiny_scene_file, tmp_path):
    out = render_scene(tiny_scene_file, tmp_path / "ds")
    for p in (out / "clean").iterdir():
        assert (out / "images" / p.name).read_bytes() == p.read_bytes()


def test_same_seed_same_bytes_other_seed_other_noise(tmp_path):
    scene = write_scene(tmp_path, NOISY)
    a = render_scene(scene, tmp_path / "a")
    b = render_scene(scene, tmp_path / "b")
    assert _digest(a) == _digest(b)  # meta.json differs only by timings
    c = render_scene(scene, tmp_path / "c", seed=4)
    da, dc = _digest(a), _digest(c)
    assert da["clean/view_000.png"] == dc["clean/view_000.png"]  # the seed drives effects only
    assert da["depth/view_000.npy"] == dc["depth/view_000.npy"]
    assert da["images/view_000.png"] != dc["images/view_000.png"]
    clean = read_image(a / "clean" / "view_001.png")
    noisy = read_image(a / "images" / "view_001.png")
    assert 0.04 < np.std(noisy - clean) < 0.12  # sigma 20/255 = 0.078 plus vignetting


def test_adding_a_view_leaves_other_views_noise_unchanged(tmp_path):
    scene = write_scene(tmp_path, NOISY)
    extra = NOISY.replace("[textures.t]", """[[rig.poses]]
position = [0.1, -0.3, 1.3]
look_at = [0.0, 4.0, 0.5]

[textures.t]""")
    assert extra != NOISY
    a = render_scene(scene, tmp_path / "a")
    b = render_scene(write_scene(tmp_path, extra, "extra.toml"), tmp_path / "b")
    assert len(list((b / "images").iterdir())) == 4
    for name in ("view_000.png", "view_001.png", "view_002.png"):
        assert (a / "images" / name).read_bytes() == (b / "images" / name).read_bytes()


def test_views_and_size_overrides_and_no_half_written_output(tmp_path):
    out = render_scene("llff_like_clean", tmp_path / "ds", size_wh=(40, 30), views=2)
    assert read_image(out / "images" / "view_001.png").shape == (30, 40, 3)
    spec = tomllib.loads((out / "scene.toml").read_text())
    assert spec["render"]["size"] == [40, 30] and spec["rig"]["views"] == 2
    bad = TINY_SCENE + '\n[[objects]]\nname = "m"\nshape = "mesh"\npath = "missing.ply"\ntexture = "t"\n'
    with pytest.raises(InputError, match="missing.ply"):
        render_scene(write_scene(tmp_path, bad, "bad.toml"), tmp_path / "bad_out")
    assert not (tmp_path / "bad_out").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_user_mesh_renders(tmp_path):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_torus(0.4, 0.15)
    o3d.io.write_triangle_mesh(str(tmp_path / "torus.ply"), mesh)
    text = TINY_SCENE + ('\n[[objects]]\nname = "torus"\nshape = "mesh"\npath = "torus.ply"\ntexture = "c"\n'
                         'translate = [0.0, 2.0, 1.0]\nrotate_deg = [90.0, 0.0, 0.0]\n')
    out = render_scene(write_scene(tmp_path, text, "torus.toml"), tmp_path / "ds")
    depth = np.load(out / "depth" / "view_000.npy")
    # The torus (at 2 m) is the nearest thing in the middle of view 0.
    assert np.nanmin(depth[18:30, 26:38]) < 2.2


def test_outputs_only_when_needed(tmp_path):
    from data_synth.dataset import render_needs

    base = TINY_SCENE.replace('outputs = ["depth", "alpha", "normals"]', "outputs = []")
    spec = load_scene(write_scene(tmp_path, base, "none.toml"))
    assert render_needs(spec) == type(render_needs(spec))(depth=False, alpha=False, normals=False)
    out = render_scene(write_scene(tmp_path, base, "none.toml"), tmp_path / "none")
    assert not (out / "depth").exists() and not (out / "alpha").exists()
    # A depth-dependent defocus makes depth necessary (computed) without writing it.
    defocus = base + '\n[[effects]]\ntype = "defocus_blur"\nradius_px = 2.0\nfocus_depth = 3.0\n'
    spec = load_scene(write_scene(tmp_path, defocus, "defocus.toml"))
    assert render_needs(spec).depth
    out = render_scene(write_scene(tmp_path, defocus, "defocus.toml"), tmp_path / "defocus")
    assert not (out / "depth").exists()
    assert (out / "images" / "view_000.png").read_bytes() != (out / "clean" / "view_000.png").read_bytes()


def test_sixteen_bit_output(tmp_path):
    from mvgeo.common.deps import cv2

    text = TINY_SCENE.replace("supersample = 2", "supersample = 2\nbit_depth = 16")
    out = render_scene(write_scene(tmp_path, text), tmp_path / "ds")
    raw = cv2.imread(str(out / "clean" / "view_000.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert len(np.unique(raw)) > 256  # real 16-bit values, not 8-bit data scaled up


def test_distorted_camera_is_written_as_opencv_and_matches_pycolmap(tmp_path):
    from data_synth import SceneRenderer, rig_views
    from data_synth.intrinsics import camera_from_spec, camera_rays, sample_positions
    from mvgeo.common.deps import pycolmap

    text = TINY_SCENE.replace("fov_x_deg = 60.0", "fov_x_deg = 60.0\ndistortion = [-0.15, 0.03, 0.001, -0.001]")
    path = write_scene(tmp_path, text)
    out = render_scene(path, tmp_path / "ds")
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    pc_cam = rec.cameras[1]
    assert pc_cam.model.name == "OPENCV"
    # Lift pixel centres with our (undistorted) rays and depth; COLMAP's OPENCV projection must
    # land back on the pixel centres (tolerance: 1e-6 px, float32 depth scales points only along rays).
    spec = load_scene(path)
    cam = camera_from_spec(spec.camera, tuple(spec.render.size))
    view = rig_views(spec.rig)[0]
    depth = SceneRenderer.from_spec(spec).render(cam, view.cam_from_world, supersample=1, depth=True).depth
    uv = sample_positions(tuple(spec.render.size), 1).reshape(-1, 2)
    dirs, valid = camera_rays(cam, uv)
    ok = valid & np.isfinite(depth.reshape(-1))
    x_cam = dirs[ok] * depth.reshape(-1)[ok, None].astype(np.float64)
    np.testing.assert_allclose(np.asarray(pc_cam.img_from_cam(x_cam)), uv[ok], atol=1e-6)
