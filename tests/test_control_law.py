"""ControlConfig / ControlLaw: stability conditions refused by name, saturation keeping the direction, stop
criterion, robustness to bad inputs, and the DVS rotational error θμ being the rotation vector."""

from __future__ import annotations

import numpy as np
import pytest

from ddvs_service.camera import Intrinsics
from ddvs_service.control.errors import dvs_error, reduced_error, vex_antisymmetric
from ddvs_service.control.law import ControlConfig, ControlLaw
from ddvs_service.control.stability import UnstableConfigurationError
from ddvs_service.lie import pose, so3_exp, so3_log, vex
from sim.ground_truth import ground_truth
from sim.surfaces import paper_saddle

INTR = Intrinsics.centred(500.0, 550, 418)


def truth(t, r, scaling: str = "sl3"):
    return ground_truth(paper_saddle(), INTR, np.eye(4), pose(so3_exp(r), t), None, scaling)


@pytest.mark.parametrize(
    ("config", "condition"),
    [
        (ControlConfig(law="ddvs", c_star=(0.0, 0.0, 2.0)), "(17)"),
        (ControlConfig(law="ddvs", c_star=(0.0, 0.0, 3.0)), "(35)"),
        (ControlConfig(law="ddvs", gains=(0.4, 0.4, -0.4, 0.4, 0.4, 0.4)), "(28)"),
        (ControlConfig(law="ddvs", gains=(0.4, 0.4, 0.4, -0.4, 0.4, 0.4)), "(27)"),
        (ControlConfig(law="ddvs", gains=(0.4, 0.4, 0.4, -0.4, 0.4, 0.4), c_star=(0.0, 0.0, 3.0)), "(27)"),
        (ControlConfig(law="ddvs", gains=(0.4, -0.4, 0.4, 0.4, 0.4, 0.4)), "(26)"),
        (ControlConfig(law="ddvs", gains=(-0.4, -0.4, 0.4, 0.4, 0.4, 0.4)), "(26)"),
        (ControlConfig(law="ddvs", q_star=(0.0, 0.0, 2.5), z_star=1.0), "(26)"),
        (ControlConfig(law="ddvs", q_star=(0.0, 0.0, 2.0), z_star=1.0), "(18)"),
        (ControlConfig(law="dvs_reduced", gains=(0.4, 0.4, 0.4, 0.4, 0.4, -0.1)), "(12)"),
        (ControlConfig(law="dvs_reduced", q_star=(0.0, 0.0, 2.5), z_star=1.0), "(34)"),
    ],
)
def test_unstable_configurations_are_refused_naming_the_condition(config: ControlConfig, condition: str) -> None:
    with pytest.raises(UnstableConfigurationError, match=condition.replace("(", r"\(").replace(")", r"\)")):
        ControlLaw(config, INTR)


def test_stable_configurations_are_accepted() -> None:
    ControlLaw(ControlConfig(law="ddvs"), INTR)
    ControlLaw(ControlConfig(law="ddvs", q_star=(0.0, 0.0, 1.0), z_star=1.0), INTR)
    # c*'ᵀm*' > 2 with negative λ4, λ5 satisfies (27)
    ControlLaw(ControlConfig(law="ddvs", gains=(0.4, 0.4, 0.4, -0.4, -0.4, 0.4), c_star=(0.0, 0.0, 3.0)), INTR)
    # negative λ1, λ2 are stable when the control point is far behind the plane (2/z* − m*'ᵀq*' < 0)
    ControlLaw(ControlConfig(law="ddvs", gains=(-0.4, -0.4, 0.4, 0.4, 0.4, 0.4), q_star=(0.0, 0.0, 2.5), z_star=1.0),
               INTR)
    ControlLaw(ControlConfig(law="dvs", gains=0.4, p_star=(100.0, 50.0)), INTR)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"law": "ibvs"},
        {"gains": (0.4, 0.4)},
        {"gains": float("nan")},
        {"max_linear": 0.0},
        {"stop_threshold": -1.0},
        {"p_star": (1.0, 2.0, 3.0)},
        {"z_star": -1.0},
    ],
)
def test_invalid_configuration_values_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        ControlConfig(**kwargs)


def test_saturation_keeps_the_twist_direction() -> None:
    gt = truth([0.17, -0.11, 0.01], [-0.1, -0.31, 1.04])
    free = ControlLaw(ControlConfig(law="ddvs"), INTR).compute(gt.G, gt.e, gt.rho)
    law = ControlLaw(ControlConfig(law="ddvs", max_linear=0.01, max_angular=0.05), INTR)
    out = law.compute(gt.G, gt.e, gt.rho)
    assert out.saturated and not free.saturated
    assert np.linalg.norm(out.twist[:3]) <= 0.01 + 1e-12 and np.linalg.norm(out.twist[3:]) <= 0.05 + 1e-12
    np.testing.assert_allclose(out.twist / np.linalg.norm(out.twist), free.twist / np.linalg.norm(free.twist))
    np.testing.assert_allclose(out.error, free.error)


def test_stop_criterion_commands_zero_twist() -> None:
    gt = truth([1e-6, 0.0, 0.0], [0.0, 0.0, 1e-6])
    out = ControlLaw(ControlConfig(law="ddvs", stop_threshold=1e-3), INTR).compute(gt.G, gt.e, gt.rho)
    assert out.converged and not out.saturated and out.error_norm < 1e-3
    assert np.all(out.twist == 0.0)
    far = ControlLaw(ControlConfig(law="ddvs", stop_threshold=1e-9), INTR).compute(gt.G, gt.e, gt.rho)
    assert not far.converged and np.linalg.norm(far.twist) > 0.0


def test_non_finite_inputs_raise_instead_of_returning_nan() -> None:
    law = ControlLaw(ControlConfig(law="dvs_reduced"), INTR)
    with pytest.raises(ValueError, match="G"):
        law.compute(np.full((3, 3), np.nan), np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="e"):
        law.compute(np.eye(3), [np.inf, 0.0, 0.0], 0.0)
    with pytest.raises(ValueError, match="rho"):
        law.compute(np.eye(3), np.zeros(3), float("nan"))


def test_laws_use_their_own_errors_and_gains() -> None:
    gt = truth([0.05, 0.02, -0.03], [0.1, -0.2, 0.3])
    m = np.array([0.0, 0.0, 1.0])
    gains = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
    out = ControlLaw(ControlConfig(law="dvs_reduced", gains=gains), INTR).compute(gt.G, gt.e, gt.rho)
    np.testing.assert_allclose(out.twist, np.array(gains) * reduced_error(gt.G, gt.e, gt.rho, INTR.K, m))
    out = ControlLaw(ControlConfig(law="dvs", gains=gains), INTR).compute(gt.G, gt.e, gt.rho)
    np.testing.assert_allclose(out.twist, np.array(gains) * dvs_error(gt.G, gt.e, gt.rho, INTR.K, m))


@pytest.mark.parametrize("angle", [0.3, 1.5, 2.5])
def test_dvs_rotational_error_is_the_rotation_vector(angle: float) -> None:
    """(9)–(11) on a pure rotation: θμ is the rotation vector of R (current from reference), both branches of (10)."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    gt = truth([0.0, 0.0, 0.0], angle * axis)
    eps = dvs_error(gt.G, gt.e, gt.rho, INTR.K, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(eps[3:], so3_log(gt.T_cur_ref[:3, :3]), atol=1e-9)


def test_vex_antisymmetric_is_vex_of_the_difference_bit_for_bit():
    rng = np.random.default_rng(11)
    for _ in range(2000):
        H = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-8.0, 3.0, size=(3, 3))
        assert np.array_equal(vex_antisymmetric(H), vex(H - H.T))
