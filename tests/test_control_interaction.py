"""The control errors against the paper's theory, with exact geometry (no images): finite differences of each
error with respect to the current camera's body twist at the equilibrium reproduce (20) and (19); the
fronto-parallel case gives (38); the closed-loop spectrum is Theorem 3.2's; singularities sit exactly where
(17)/(18) fail; and `ε_v = (R − I) m*' + t/z*` under the Euclidean scaling pins frames and signs."""

from __future__ import annotations

import numpy as np
import pytest

from ddvs_service.camera import Intrinsics
from ddvs_service.control.errors import decoupled_error, decoupling_matrix, reduced_error, translation_error
from ddvs_service.control.interaction import (
    L_bar_equilibrium,
    L_prime_equilibrium,
    closed_loop_matrix,
    theorem_3_2_spectrum,
)
from ddvs_service.lie import pose, se3_exp, so3_exp
from sim.ground_truth import ground_truth
from sim.surfaces import Plane, Saddle, paper_saddle

INTR = Intrinsics.centred(500.0, 550, 418)


def random_plane(rng: np.random.Generator) -> Plane:
    """A plane 0.5–2 m in front of the reference camera (world = reference frame), tilted up to ~40°."""
    R = so3_exp(rng.normal(scale=0.4, size=3)) @ so3_exp([np.pi, 0.0, 0.0])  # local +z roughly towards the camera
    centre = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.5, 2.0)])
    return Plane(pose(R, centre), (3.0, 3.0))


def random_saddle(rng: np.random.Generator) -> Saddle:
    T = pose(so3_exp(rng.normal(scale=0.05, size=3)), [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 1.0])
    return Saddle(T, (2.0, 2.0), a=rng.uniform(0.8, 2.0))


def fd_interaction(error, surface, p_star, scaling: str, h: float = 1e-5) -> np.ndarray:
    """Central finite differences of `error(G, e, rho)` wrt the current camera's body twist at the equilibrium."""
    T_ref = np.eye(4)
    L = np.zeros((6, 6))
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = h
        cols = []
        for sign in (1.0, -1.0):
            gt = ground_truth(surface, INTR, T_ref, T_ref @ se3_exp(sign * xi), p_star, scaling)
            cols.append(error(gt.G, gt.e, gt.rho))
        L[:, i] = (cols[0] - cols[1]) / (2.0 * h)
    return L


def assert_rel(actual: np.ndarray, expected: np.ndarray, tol: float) -> None:
    rel = np.linalg.norm(actual - expected) / np.linalg.norm(expected)
    assert rel < tol, f"relative difference {rel:.3g} ≥ {tol}\nactual\n{actual}\nexpected\n{expected}"


def scenes(seed: int):
    rng = np.random.default_rng(seed)
    for k in range(6):
        surface = random_plane(rng) if k % 2 == 0 else random_saddle(rng)
        p_star = (rng.uniform(100, 450), rng.uniform(80, 340))
        c_star = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0.5, 1.5)])
        yield surface, p_star, c_star


@pytest.mark.parametrize("seed", [1, 2])
def test_finite_differences_match_L_prime_and_L_bar(seed: int) -> None:
    for surface, p_star, c_star in scenes(seed):
        m = INTR.normalize(p_star)
        gt = ground_truth(surface, INTR, np.eye(4), np.eye(4), p_star, "euclidean")
        L_prime = fd_interaction(lambda G, e, r, m=m: reduced_error(G, e, r, INTR.K, m), surface, p_star, "euclidean")
        assert_rel(L_prime, L_prime_equilibrium(m, gt.q_star, gt.z_star), 1e-6)
        L_bar = fd_interaction(
            lambda G, e, r, m=m, c=c_star: decoupled_error(G, e, r, INTR.K, m, c), surface, p_star, "euclidean"
        )
        assert_rel(L_bar, L_bar_equilibrium(m, gt.q_star, gt.z_star, c_star), 1e-6)
        assert_rel(decoupling_matrix(m, c_star) @ L_prime_equilibrium(m, gt.q_star, gt.z_star), L_bar, 1e-6)


def test_sl3_scaling_adds_m_qT_over_3_to_the_translational_block() -> None:
    """Finding: with det G = 1 the normalisation factor det(R + t n*ᵀ)^(-1/3) has a first-order variation, so the
    interaction matrix of ε' at the equilibrium is (20) plus `m*' q*'ᵀ/3` in its top-left block."""
    for surface, p_star, _ in scenes(3):
        m = INTR.normalize(p_star)
        gt = ground_truth(surface, INTR, np.eye(4), np.eye(4), p_star, "sl3")
        L = fd_interaction(lambda G, e, r, m=m: reduced_error(G, e, r, INTR.K, m), surface, p_star, "sl3")
        expected = L_prime_equilibrium(m, gt.q_star, gt.z_star)
        expected[:3, :3] += np.outer(m, gt.q_star) / 3.0
        assert_rel(L, expected, 1e-6)


def test_fronto_parallel_gives_the_diagonal_matrix_38() -> None:
    d = 0.8
    plane = Plane(pose(so3_exp([np.pi, 0.0, 0.0]), [0.05, -0.02, d]), (3.0, 3.0))  # normal towards the camera
    m = np.array([0.0, 0.0, 1.0])
    L_bar = fd_interaction(lambda G, e, r: decoupled_error(G, e, r, INTR.K, m, m), plane, None, "euclidean")
    assert_rel(L_bar, -np.diag([1 / d, 1 / d, 2 / d, 1.0, 1.0, 2.0]), 1e-6)


def test_closed_loop_spectrum_matches_theorem_3_2() -> None:
    rng = np.random.default_rng(4)
    for _ in range(20):
        q = rng.normal(scale=0.5, size=3)
        z = rng.uniform(0.5, 2.0)
        c = rng.normal(scale=0.7, size=3)
        gains = rng.uniform(-1.0, 1.0, size=6)
        # Theorem 3.2's closed form: m*' = [0, 0, 1] with any per-axis gains ...
        m = np.array([0.0, 0.0, 1.0])
        eig = np.linalg.eigvals(closed_loop_matrix(L_bar_equilibrium(m, q, z, c), gains))
        np.testing.assert_allclose(
            np.sort_complex(eig), np.sort_complex(theorem_3_2_spectrum(m, q, z, c, gains)), rtol=1e-9, atol=1e-9
        )
        # ... or any m*' with one gain per block (the proof rotates m*' onto the optical axis).
        m = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), 1.0])
        block = np.repeat(rng.uniform(0.1, 1.0, size=2), 3)
        eig = np.linalg.eigvals(closed_loop_matrix(L_bar_equilibrium(m, q, z, c), block))
        np.testing.assert_allclose(
            np.sort_complex(eig), np.sort_complex(theorem_3_2_spectrum(m, q, z, c, block)), rtol=1e-9, atol=1e-9
        )


def test_singular_exactly_where_17_or_18_fail() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        m = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), 1.0])
        q = rng.normal(scale=0.5, size=3)
        c = rng.normal(scale=0.7, size=3)
        z = rng.uniform(0.5, 2.0)
        mc, mq = m @ c, m @ q
        np.testing.assert_allclose(np.linalg.det(decoupling_matrix(m, c)), 2.0 * (2.0 - mc) ** 2, rtol=1e-9)
        np.testing.assert_allclose(
            np.linalg.det(L_prime_equilibrium(m, q, z)), 8.0 * (1 / z - mq / 2) ** 2 / z, rtol=1e-9, atol=1e-12
        )
        assert np.linalg.svd(L_bar_equilibrium(m, q, z, c), compute_uv=False)[-1] > 1e-6
        c17 = c + (2.0 - mc) * m / (m @ m)  # now m*'ᵀc*' = 2: (17) fails
        q18 = q + (2.0 / z - mq) * m / (m @ m)  # now m*'ᵀq*' = 2/z*: (18) fails
        assert np.linalg.svd(decoupling_matrix(m, c17), compute_uv=False)[-1] < 1e-12
        assert np.linalg.svd(L_bar_equilibrium(m, q, z, c17), compute_uv=False)[-1] < 1e-12
        assert np.linalg.svd(L_bar_equilibrium(m, q18, z, c), compute_uv=False)[-1] < 1e-12
        assert np.linalg.svd(L_prime_equilibrium(m, q18, z), compute_uv=False)[-1] < 1e-12


def test_translation_error_is_R_minus_I_m_plus_t_over_z_under_euclidean_scaling() -> None:
    rng = np.random.default_rng(6)
    saddle = paper_saddle()
    for _ in range(10):
        p_star = (rng.uniform(150, 400), rng.uniform(100, 300))
        T_ref_cur = pose(so3_exp(rng.normal(scale=0.3, size=3)), rng.normal(scale=0.1, size=3))
        gt = ground_truth(saddle, INTR, np.eye(4), T_ref_cur, p_star, "euclidean")
        m = INTR.normalize(p_star)
        H = INTR.K_inv @ gt.G @ INTR.K
        R, t = gt.T_cur_ref[:3, :3], gt.T_cur_ref[:3, 3]
        np.testing.assert_allclose(
            translation_error(H, INTR.K_inv @ gt.e, gt.rho, m), (R - np.eye(3)) @ m + t / gt.z_star, atol=1e-12
        )
        # the model (2) itself: the control point's 3-D point reprojects to G p* + ρ* e
        X = R @ (gt.z_star * m) + t
        p = gt.G @ INTR.K @ m + gt.rho * gt.e
        np.testing.assert_allclose(p / p[2], INTR.K @ X / X[2], atol=1e-9)
