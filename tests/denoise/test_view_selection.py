"""k-means and pose-based view selection."""

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from denoise.kmeans import kmeans, kmeans_pp_init
from denoise.view_selection import laplacian_variance, pose_features, select_views
from mvgeo.common.errors import InputError


def _brute_force_best_inertia(x, k):
    """Optimal k-means by enumerating every assignment (tiny N only)."""
    best = np.inf
    for labels in itertools.product(range(k), repeat=len(x)):
        labels = np.array(labels)
        if len(set(labels.tolist())) != k:
            continue
        inertia = sum(np.sum((x[labels == j] - x[labels == j].mean(0)) ** 2) for j in range(k))
        best = min(best, inertia)
    return best


def test_kmeans_matches_brute_force(rng):
    for trial in range(3):
        x = rng.standard_normal((6, 2)) + rng.integers(0, 3, (6, 1)) * 4.0
        res = kmeans(x, 3, seed=trial, restarts=10)
        # Lloyd + 10 k-means++ restarts reaches the global optimum on 6 points (checked exhaustively).
        assert res.inertia == pytest.approx(_brute_force_best_inertia(x, 3), rel=1e-9)
        assert sorted(set(res.labels.tolist())) == [0, 1, 2]
        assert res.labels[0] == 0  # renumbered by first appearance


def test_kmeans_duplicates_and_k_equals_n():
    x = np.zeros((5, 3))
    x[3:] = 1.0
    res = kmeans(x, 5, seed=0)
    assert sorted(res.labels.tolist()) == [0, 1, 2, 3, 4]  # every cluster non-empty
    init = kmeans_pp_init(x, 4, np.random.default_rng(0))
    assert init.shape == (4, 3)
    with pytest.raises(ValueError):
        kmeans(x, 6)


def _ring_poses(n, radius=3.0, centre=(0.0, 0.0, 0.0)):
    """Cameras on a circle in the xz-plane looking at `centre`; returns (n, 3, 4) cam_from_world."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / n
        c = np.array(centre) + radius * np.array([np.cos(a), 0.0, np.sin(a)])
        z = np.array(centre) - c
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])  # rows = camera axes in world -> world_from_cam^T
        poses.append(np.concatenate([R, (-R @ c)[:, None]], axis=1))
    return np.array(poses)


def test_pose_features_centres_and_forward():
    poses = _ring_poses(8, radius=5.0, centre=(10.0, 2.0, -3.0))
    f, scale = pose_features(poses)
    assert scale == pytest.approx(5.0)  # every centre is 5 from the mean
    np.testing.assert_allclose(np.linalg.norm(f[:, :3], axis=1), 1.0, atol=1e-12)
    # Forward axis points at the ring centre: equals minus the normalised centre offset.
    np.testing.assert_allclose(f[:, 3:], -f[:, :3], atol=1e-12)
    # Invariant to a similarity change of the world frame (scale, rotation, translation).
    Rw = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    s, tw = 7.0, np.array([1.0, 2.0, 3.0])
    # x_w' = s Rw x_w + tw  ->  cam_from_world' = [R Rw^T, s t - R Rw^T tw] (up to the camera scale s).
    moved = np.array([np.concatenate([P[:, :3] @ Rw.T, (s * P[:, 3] - P[:, :3] @ Rw.T @ tw)[:, None]], 1)
                      for P in poses])
    f2, scale2 = pose_features(moved)
    assert scale2 == pytest.approx(35.0)
    np.testing.assert_allclose(f2[:, :3], f[:, :3] @ Rw.T, atol=1e-9)
    np.testing.assert_allclose(f2[:, 3:], f[:, 3:] @ Rw.T, atol=1e-12)


def test_pose_features_pure_rotation():
    R = Rotation.from_rotvec(np.array([[0, 0.1 * i, 0] for i in range(4)])).as_matrix()
    poses = np.concatenate([R, np.zeros((4, 3, 1))], axis=2)
    f, scale = pose_features(poses)
    assert scale == 0.0 and np.all(f[:, :3] == 0)


def _textured(rng, sharp, h=32, w=32):
    img = rng.random((h, w, 3)).astype(np.float32)
    if not sharp:
        img = np.full_like(img, img.mean())
        img += 0.001 * rng.random((h, w, 3)).astype(np.float32)
    return img


def test_select_views_one_sharpest_per_group(rng):
    # Three tight groups of 4 cameras on a ring; in each group exactly one image is sharp.
    ring = _ring_poses(3)
    poses, names, images = {}, [], {}
    for g in range(3):
        for j in range(4):
            jitter = Rotation.from_rotvec(0.01 * rng.standard_normal(3)).as_matrix()
            P = ring[g].copy()
            P[:, :3] = jitter @ P[:, :3]
            name = f"g{g}_{j}.png"
            poses[name] = P
            images[name] = _textured(rng, sharp=(j == (g + 1) % 4))
            names.append(name)
    sel = select_views(poses, images, k=3, seed=0)
    assert sel.names == ["g0_1.png", "g1_2.png", "g2_3.png"]
    groups = {g: {sel.cluster_of[f"g{g}_{j}.png"] for j in range(4)} for g in range(3)}
    assert all(len(v) == 1 for v in groups.values()) and len({next(iter(v)) for v in groups.values()}) == 3
    assert sel.k == 3
    d = sel.to_json_dict()
    assert d["selected"] == sel.names and d["views"]["g0_1.png"]["selected"] is True
    # Seeded: same answer again.
    assert select_views(poses, images, k=3, seed=0) == sel


def test_select_views_k_at_least_n_keeps_all(rng):
    poses = _ring_poses(5)
    imgs = [_textured(rng, True) for _ in range(5)]
    sel = select_views(poses, imgs, k=12, names=list("abcde"))
    assert sel.names == list("abcde") and sel.k == 5


def test_select_views_errors(rng):
    poses = _ring_poses(3)
    with pytest.raises(InputError):
        select_views({}, {}, k=2)
    with pytest.raises(InputError):
        select_views({"a": poses[0]}, {"b": _textured(rng, True)}, k=1)
    with pytest.raises(InputError):
        select_views(poses, [_textured(rng, True)], k=1)
    with pytest.raises(InputError):
        select_views({"a": poses[0]}, {"a": "/nonexistent/a.png"}, k=1)


def test_laplacian_variance_reference(rng):
    img = rng.random((9, 8)).astype(np.float32)
    p = np.pad(img.astype(np.float64), 1, mode="reflect")  # OpenCV's default border is reflect-101
    lap = p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * p[1:-1, 1:-1]
    assert laplacian_variance(img) == pytest.approx(lap.var(), rel=1e-5)  # float32 filter vs float64
    assert laplacian_variance(np.full((5, 5, 3), 0.5, np.float32)) == 0.0
