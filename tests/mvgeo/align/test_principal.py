"""`mvgeo.align.principal`: the principal point estimated for an accepted solution, kept where the views
determine it."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from mvgeo.align.bundle import BundleConfig, bundle_adjust
from mvgeo.align.config import AlignConfig
from mvgeo.align.principal import MAX_STD_DEG, MIN_CHI2, determined, estimate_principal, with_principal_point
from mvgeo.common.errors import ConfigError
from mvgeo.common.timing import StageTimer
from mvgeo.transforms import so3_exp

from .test_bundle_lm import H, W, _matches, _ring


@pytest.mark.parametrize("offset, std, focal, kept", [
    # The measured figures (docs/bench/principal_point.md, undithered), alignment pixels:
    ((-16.6, 9.7), (1.9, 3.3), 1535.0, True),     # temple ring, clean: 0.12 deg, chi-square 88.6
    ((7.3, 13.6), (5.4, 6.7), 920.0, False),      # DTU scan24, clean: 0.41 deg (too loose)
    ((3.2, -11.7), (13.0, 15.8), 920.0, False),   # DTU scan24, sigma 25: 0.98 deg
    ((-0.4, 1.1), (0.8, 0.9), 411.0, False),      # llff_like (true principal point at the centre): chi-square 1.6
])
def test_the_rule_keeps_a_principal_point_only_where_it_is_determined(offset, std, focal, kept):
    ok, why = determined(np.array(offset), np.array(std), focal)
    assert ok is kept
    assert "deg of view angle" in why and "chi-square" in why


def test_the_rules_two_conditions():
    focal = 1000.0
    tight = np.tan(np.radians(0.5 * MAX_STD_DEG)) * focal  # half the allowed standard deviation
    assert determined(np.array([10 * tight, 0.0]), np.array([tight, tight]), focal)[0]
    # Determined but not off the centre (chi-square 4 < 9.21): the centre stays.
    assert not determined(np.array([2 * tight, 0.0]), np.array([tight, tight]), focal)[0]
    assert MIN_CHI2 == pytest.approx(9.21)  # chi-square, 2 degrees of freedom, 99 %
    # Far off the centre but loose: the centre stays.
    assert not determined(np.array([100 * tight, 0.0]), np.array([3 * tight, tight]), focal)[0]


def _adjusted_ring(rng, c_true):
    X, poses, uv, f, c_true = _ring(rng, c_true=c_true)
    start = poses.copy()
    for k in range(1, len(start)):
        start[k, :, :3] = so3_exp(rng.normal(scale=0.01, size=3)) @ start[k, :, :3]
    ba = bundle_adjust(start, np.full(len(poses), f), (W, H), _matches(uv),
                       config=BundleConfig(max_points=1000, readjust_min_gain=0.0))
    return SimpleNamespace(ba=ba, inputs=SimpleNamespace(K_align=None, align_wh=(W, H))), c_true


def test_a_ring_with_its_principal_point_off_the_centre_determines_it(rng):
    """From the bundle adjustment with the centre assumed, the estimate recovers the true principal point
    (17 px off) to within three standard deviations and is kept."""
    c, c_true = _adjusted_ring(rng, (W / 2 - 14.0, H / 2 + 9.0))
    est = estimate_principal(c, AlignConfig())
    assert est.determined, est.why
    assert np.all(np.abs(est.principal_px - c_true) < 3 * est.std_px + 1e-3)
    np.testing.assert_allclose(est.offset_px, est.principal_px - [W / 2, H / 2])


def test_a_ring_with_its_principal_point_at_the_centre_keeps_the_centre(rng):
    c, _ = _adjusted_ring(rng, (W / 2, H / 2))
    est = estimate_principal(c, AlignConfig())
    assert not est.determined and "chi-square" in est.why
    assert np.all(np.abs(est.offset_px) < 3 * est.std_px)


def test_known_intrinsics_a_refused_solution_and_the_centre_setting_are_left_alone(rng):
    c, _ = _adjusted_ring(rng, (W / 2 - 14.0, H / 2 + 9.0))
    known = SimpleNamespace(ba=c.ba, inputs=SimpleNamespace(K_align=np.eye(3)[None], align_wh=(W, H)))
    assert estimate_principal(known, AlignConfig()) is None
    accepted = SimpleNamespace(verdict=SimpleNamespace(ok=True))
    refused = SimpleNamespace(verdict=SimpleNamespace(ok=False))
    assert with_principal_point(refused, AlignConfig(), StageTimer()) == (refused, None)
    assert with_principal_point(accepted, AlignConfig(principal_point="centre"), StageTimer()) == (accepted, None)
    with pytest.raises(ConfigError, match="principal_point"):
        replace(AlignConfig(), principal_point="center")
    # The candidates' adjustment keeps it fixed: their verdict, stereo and cameras assume the given one.
    with pytest.raises(ConfigError, match="bundle.refine_principal"):
        AlignConfig(bundle=BundleConfig(refine_principal=True))


def test_a_kept_principal_point_reaches_the_cameras_and_the_cloud():
    """An estimated principal point travels as K_align without intrinsics: the output cameras carry it at the
    input size, with the solution's focal (`api._sparse_model`), and the cloud's grids use it
    (`cloud._principal`); without it, the centre."""
    from mvgeo.align.api import _sparse_model
    from mvgeo.align.cloud import _principal
    from mvgeo.align.inputs import AlignInputs

    K = np.array([[300.0, 0.0, 150.0], [0.0, 300.0, 130.0], [0.0, 0.0, 1.0]])  # alignment size 320 x 240
    inputs = AlignInputs(["a.png", "b.png"], [None, None], [None, None], (640, 480), (320, 240), None,
                         np.repeat(K[None], 2, axis=0))
    result = SimpleNamespace(depth=[np.zeros((72, 96))], focal_px=np.array([90.0, 90.0]),
                             cam_from_world=np.repeat(np.eye(4)[None, :3], 2, axis=0))
    cloud = SimpleNamespace(xyz=np.zeros((0, 3)), rgb=np.zeros((0, 3)))
    graph = SimpleNamespace(grid_to_align=320 / 96)  # alignment pixels per pointmap pixel
    cams = _sparse_model(SimpleNamespace(inputs=inputs, result=result, graph=graph), cloud).cameras
    assert len(cams) == 1
    cam = cams[1]
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [90.0 * 640 / 96, 90.0 * 480 / 72, 300.0, 260.0])
    assert _principal(inputs) == [(150.0, 130.0)] * 2
    centred = replace(inputs, K_align=None)
    assert _principal(centred) == [(160.0, 120.0)] * 2
    cam = _sparse_model(SimpleNamespace(inputs=centred, result=result, graph=graph), cloud).cameras[1]
    np.testing.assert_allclose([cam.cx, cam.cy], [320.0, 240.0])
