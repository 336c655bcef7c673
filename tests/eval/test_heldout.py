"""Held-out camera mapping through a Sim(3) fitted on training cameras."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eval.heldout import map_cameras, register_sim3
from mvgeo.common.errors import DegenerateGeometryError, InputError


def _look_at_rig(rng, n, *, collinear=False):
    """Forward-facing cameras around the origin looking at (0, 0, 4)."""
    cams = {}
    for i in range(n):
        c = np.array([0.3 * i - 0.5, 0.0 if collinear else rng.normal(0, 0.2), rng.normal(0, 0.05) * (not collinear)])
        R = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
        cams[f"v{i:02d}"] = np.hstack([R, (-R @ c)[:, None]])
    return cams


def _random_sim3(rng):
    return 0.37, Rotation.from_rotvec(rng.normal(0, 1.0, 3)).as_matrix(), rng.normal(0, 2.0, 3)


def _to_est(cfw, s, R, t):
    """The exact camera of `cfw` in a world where x_est = s R x_ref + t."""
    Rn = cfw[:, :3] @ R.T
    return np.hstack([Rn, (s * cfw[:, 3] - Rn @ t)[:, None]])


def _project(cfw, X):
    x = X @ cfw[:, :3].T + cfw[:, 3]
    return x[:, :2] / x[:, 2:]


@pytest.mark.parametrize("collinear", [False, True])
def test_exact_similarity_is_recovered_and_pixels_agree(collinear):
    rng = np.random.default_rng(0)
    ref = _look_at_rig(rng, 8, collinear=collinear)
    s, R, t = _random_sim3(rng)
    train = [n for i, n in enumerate(ref) if i % 4 != 0]
    test = [n for i, n in enumerate(ref) if i % 4 == 0]
    est_train = {n: _to_est(ref[n], s, R, t) for n in train}
    m = map_cameras(est_train, {n: ref[n] for n in train}, {n: ref[n] for n in test})
    assert m.used_orientations == collinear
    # Exact data: the fit is exact up to float64 rounding of an SVD (~1e-12).
    assert m.est_from_ref.scale == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(m.est_from_ref.R, R, atol=1e-9)
    assert m.registration_rmse < 1e-9
    # Independent check: a world point seen by the true held-out camera lands on the same
    # pixel (normalised coordinates) through the mapped camera and the mapped point.
    X_ref = rng.normal(0, 0.5, (50, 3)) + [0, 0, 4]
    X_est = s * X_ref @ R.T + t
    for n in test:
        np.testing.assert_allclose(_project(m.cam_from_world[n], X_est), _project(ref[n], X_ref), atol=1e-9)


def test_noisy_estimate_maps_close():
    rng = np.random.default_rng(1)
    ref = _look_at_rig(rng, 10)
    s, R, t = _random_sim3(rng)
    train, test = list(ref)[1:], list(ref)[:1]
    est_train = {}
    for n in train:
        e = _to_est(ref[n], s, R, t)
        e[:, 3] += rng.normal(0, 1e-3, 3)  # ~1 mm in est units (scale 0.37)
        est_train[n] = e
    m = map_cameras(est_train, {n: ref[n] for n in train}, {n: ref[n] for n in test})
    # Centre noise 1e-3 est units ~ 2.7e-3 ref units per camera; RMSE must be of that order.
    assert 1e-4 < m.registration_rmse < 1e-2
    X_ref = rng.normal(0, 0.5, (50, 3)) + [0, 0, 4]
    err = _project(m.cam_from_world[test[0]], s * X_ref @ R.T + t) - _project(ref[test[0]], X_ref)
    assert np.abs(err).max() < 5e-3  # normalised image units (~2 px at f = 400)


def test_degenerate_and_bad_inputs():
    rng = np.random.default_rng(2)
    ref = _look_at_rig(rng, 4)
    with pytest.raises(DegenerateGeometryError):
        register_sim3({"v00": ref["v00"]}, ref)
    same = {n: ref["v00"] for n in ref}
    with pytest.raises(DegenerateGeometryError, match="coincide"):
        register_sim3(same, ref)
    with pytest.raises(InputError, match="both"):
        map_cameras(ref, ref, {"v00": ref["v00"]})


def test_local_mapping_equals_global_for_an_exact_similarity_and_beats_it_under_distortion():
    from eval.heldout import map_cameras_local

    rng = np.random.default_rng(3)
    ref = _look_at_rig(rng, 9)
    held = {k: ref.pop(k) for k in ("v04", "v08")}
    s, R, t = _random_sim3(rng)
    est = {k: _to_est(v, s, R, t) for k, v in ref.items()}
    loc = map_cameras_local(est, ref, held)
    for k, v in held.items():
        # Exact similarity: relative placement reproduces the exact camera (float64 rounding only).
        np.testing.assert_allclose(loc.cam_from_world[k], _to_est(v, s, R, t), atol=1e-9)
    # A distorted reconstruction (camera centres bent away from a similarity, growing with |x|):
    # the camera next to v04 carries the local distortion, so the local mapping lands closer.
    bent = {}
    for k, v in est.items():
        c = -v[:, :3].T @ v[:, 3]
        c = c + np.array([0.0, 0.0, 0.3]) * (c[0] ** 2)
        bent[k] = np.hstack([v[:, :3], (-v[:, :3] @ c)[:, None]])
    truth = _to_est(held["v04"], s, R, t)
    c_true = -truth[:, :3].T @ truth[:, 3]
    c_true = c_true + np.array([0.0, 0.0, 0.3]) * (c_true[0] ** 2)
    err = lambda m: np.linalg.norm(-m[:, :3].T @ m[:, 3] - c_true)  # noqa: E731
    assert err(map_cameras_local(bent, ref, held).cam_from_world["v04"]) < err(
        map_cameras(bent, ref, held).cam_from_world["v04"])


@pytest.mark.parametrize("jitter", [1e-4, 1e-3, 1e-2])
def test_nearly_collinear_centres_take_the_rotation_from_the_orientations(jitter):
    # A line of cameras whose centres leave it by a little: the roll about the line is set by the centres' noise
    # (5-26 deg off through Umeyama alone), the cameras' orientations fix it.
    rng = np.random.default_rng(4)
    ref = {}
    for i in range(8):
        c = np.array([6.0 * i / 7 - 3.0, 0.0, 0.0]) + rng.normal(0, jitter, 3)
        R0 = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
        ref[f"v{i:02d}"] = np.hstack([R0, (-R0 @ c)[:, None]])
    s, R, t = _random_sim3(rng)
    train, test = [n for i, n in enumerate(ref) if i != 3], ["v03"]
    est = {}
    for n in train:
        e = _to_est(ref[n], s, R, t)
        d = Rotation.from_rotvec(rng.normal(0, np.radians(0.05), 3)).as_matrix()
        c = -e[:, :3].T @ e[:, 3] + rng.normal(0, 1e-3, 3)
        est[n] = np.hstack([d @ e[:, :3], (-(d @ e[:, :3]) @ c)[:, None]])
    m = map_cameras(est, {n: ref[n] for n in train}, {n: ref[n] for n in test})
    assert m.used_orientations
    truth = _to_est(ref["v03"], s, R, t)
    err = np.degrees(Rotation.from_matrix(m.cam_from_world["v03"][:, :3] @ truth[:, :3].T).magnitude())
    assert err < 0.5, err  # the orientations' own noise is 0.05 deg per camera
