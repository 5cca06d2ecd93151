"""`ddvs_service.lie`: the matrix exponential and the sl(3) helpers, against closed forms and a long Taylor series."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ddvs_service.lie import SL3_GENERATORS, det3, expm, inv3, sl3_exp, sl3_hat, sl3_normalize, so3_exp


def taylor_reference(A: np.ndarray, terms: int = 60) -> np.ndarray:
    """exp(A) by a 60-term Taylor series after scaling to ‖X‖₁ ≤ 1/16, then squaring (float64)."""
    s = max(0, math.ceil(math.log2(max(np.linalg.norm(A, 1), 1e-300) * 16)))
    X = A / 2.0**s
    E, term = np.eye(3), np.eye(3)
    for k in range(1, terms):
        term = term @ X / k
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


@pytest.mark.parametrize("norm", [0.0, 1e-9, 1e-4, 1e-2, 0.3, 0.5, 0.51, 2.0, 7.0])
def test_expm_matches_a_long_series(norm):
    rng = np.random.default_rng(3)
    for _ in range(20):
        A = rng.normal(size=(3, 3))
        A *= norm / np.linalg.norm(A, 1)
        ref = taylor_reference(A)
        assert np.allclose(expm(A), ref, rtol=1e-13, atol=1e-14 * np.abs(ref).max()), norm


def test_expm_closed_forms():
    w = np.array([0.3, -1.2, 2.0])
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    assert np.allclose(expm(W), so3_exp(w), atol=1e-14)
    N = np.array([[0.0, 2.5, -1.0], [0.0, 0.0, 3.0], [0.0, 0.0, 0.0]])  # nilpotent: exp = I + N + N²/2
    assert np.allclose(expm(N), np.eye(3) + N + N @ N / 2, atol=1e-13)
    assert np.allclose(expm(np.diag([0.2, -3.0, 1e-6])), np.diag(np.exp([0.2, -3.0, 1e-6])), rtol=1e-14)


def test_sl3_hat_and_exp():
    x = np.array([0.1, -0.2, 0.03, 0.04, -0.05, 0.06, 1e-3, -2e-3])
    assert np.allclose(sl3_hat(x), np.einsum("i,ijk->jk", x, SL3_GENERATORS))
    G = sl3_exp(x)
    assert abs(np.linalg.det(G) - 1.0) < 1e-13
    assert np.allclose(G @ sl3_exp(-x), np.eye(3), atol=1e-13)


def test_det3_inv3_and_sl3_normalize_agree_with_lapack():
    rng = np.random.default_rng(5)
    for _ in range(200):
        A = rng.normal(size=(3, 3)) * rng.choice([1e-3, 1.0, 300.0], size=(3, 3))  # homography-like scales
        d = np.linalg.det(A)
        assert det3(A) == pytest.approx(d, rel=1e-12, abs=1e-12 * np.abs(A).max() ** 3)
        if abs(d) > 1e-6 * np.abs(A).max() ** 3:  # well away from singular
            np.testing.assert_allclose(inv3(A) @ A, np.eye(3), atol=1e-9)
        G = sl3_exp(rng.normal(size=8) * 0.3)
        np.testing.assert_allclose(inv3(G), np.linalg.inv(G), rtol=1e-12, atol=1e-14)
        assert np.linalg.det(sl3_normalize(5.0 * G)) == pytest.approx(1.0, abs=1e-13)
    with pytest.raises(ValueError, match="determinant"):
        sl3_normalize(-np.eye(3))
