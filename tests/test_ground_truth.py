"""Ground truth G, e, ρ*: the plane-plus-parallax model (2) reproduces the true projection of every reference pixel,
in both scale gauges; the gauge conventions (det G = 1, plane through the saddle centre, ρ* = 0 on a target plane,
ρ* independent of the current pose) hold."""

from __future__ import annotations

import numpy as np
import pytest

from ddvs_service.camera import Intrinsics
from ddvs_service.lie import pose, pose_inv, so3_exp
from sim.ground_truth import ground_truth, homography_and_epipole, parallax_map
from sim.surfaces import Plane, Saddle, paper_saddle

INTR = Intrinsics.centred(500.0, 110, 84)  # small image: every pixel is checked


def pixels() -> np.ndarray:
    u, v = np.meshgrid(np.arange(INTR.width, dtype=float), np.arange(INTR.height, dtype=float))
    return np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)


SURFACES = {
    "saddle": paper_saddle(),
    "tilted saddle": Saddle(pose(so3_exp([0.1, -0.2, 0.05]), [0.05, 0.02, 0.9]), (1.0, 1.0), a=0.7),
    "plane": Plane(pose(so3_exp([np.pi + 0.3, 0.2, 0.1]), [0.1, -0.05, 0.8]), (1.0, 1.0)),
}


@pytest.mark.parametrize("name", sorted(SURFACES))
@pytest.mark.parametrize("scaling", ["sl3", "euclidean"])
def test_plane_plus_parallax_reproduces_the_projection_of_every_pixel(name: str, scaling: str) -> None:
    surface = SURFACES[name]
    T_ref = pose(so3_exp([0.02, -0.01, 0.03]), [0.01, 0.0, -0.02])
    T_cur = T_ref @ pose(so3_exp([-0.1, -0.31, 1.04]), [0.17, -0.11, 0.01])
    p_ref = pixels()
    m_ref = p_ref @ INTR.K_inv.T
    depth = surface.intersect(T_ref, m_ref)
    assert np.all(np.isfinite(depth))
    X_cur = (pose_inv(T_cur) @ T_ref @ np.c_[m_ref * depth[:, None], np.ones(len(depth))].T)[:3].T
    expected = X_cur @ INTR.K.T
    rho = parallax_map(surface, INTR, T_ref).ravel()
    gt = ground_truth(surface, INTR, T_ref, T_cur, None, scaling)
    predicted = p_ref @ gt.G.T + rho[:, None] * gt.e
    np.testing.assert_allclose(predicted[:, :2] / predicted[:, 2:], expected[:, :2] / expected[:, 2:], atol=1e-9)
    if scaling == "euclidean":  # G p* + ρ* e = K X / Z*: the homogeneous scale is the Euclidean one
        np.testing.assert_allclose(predicted, expected / depth[:, None], rtol=1e-9)
    else:
        assert np.linalg.det(gt.G) == pytest.approx(1.0, abs=1e-12)


def test_gauges_of_the_paper_saddle_and_of_planes() -> None:
    saddle = paper_saddle()
    gt = ground_truth(saddle, INTR, np.eye(4), pose(so3_exp([0.1, 0.2, 0.3]), [0.05, 0.0, 0.1]))
    np.testing.assert_allclose(gt.q_star, [0.0, 0.0, 1.0])  # plane Z = 1 m through the saddle centre
    assert gt.z_star == pytest.approx(1.0) and gt.rho == pytest.approx(0.0, abs=1e-15)  # centre lies on it
    rho = parallax_map(saddle, INTR, np.eye(4))
    assert np.ptp(rho) > 1e-3  # non-planar: the parallax varies
    plane = SURFACES["plane"]
    np.testing.assert_allclose(parallax_map(plane, INTR, np.eye(4)), 0.0, atol=1e-12)  # ρ* = 0 on the target plane


def test_parallax_does_not_depend_on_the_current_pose_and_G_is_identity_at_the_reference() -> None:
    saddle = paper_saddle()
    p = (30.0, 70.0)
    a = ground_truth(saddle, INTR, np.eye(4), pose(so3_exp([0.3, 0.0, 0.0]), [0.1, 0.0, 0.0]), p)
    b = ground_truth(saddle, INTR, np.eye(4), pose(so3_exp([0.0, -0.4, 0.2]), [0.0, 0.1, -0.1]), p)
    assert a.rho == b.rho and a.z_star == b.z_star
    eq = ground_truth(saddle, INTR, np.eye(4), np.eye(4), p)
    np.testing.assert_allclose(eq.G, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(eq.e, 0.0, atol=1e-15)


def test_refuses_a_camera_behind_the_plane_and_unknown_gauges() -> None:
    n = np.array([0.0, 0.0, 1.0])
    behind = pose(np.eye(3), [0.0, 0.0, 2.0])  # current camera beyond the plane Z = 1
    with pytest.raises(ValueError, match="reference side"):
        homography_and_epipole(pose_inv(behind), n, INTR.K)
    with pytest.raises(ValueError, match="scaling"):
        homography_and_epipole(np.eye(4), n, INTR.K, "projective")
