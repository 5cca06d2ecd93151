"""Configuration-time checks of the control laws against Theorems 3.1 and 3.2 (docs/equations.md: (17), (18), (26)–(28),
(34), (35)); a configuration that cannot be locally stable is refused with `UnstableConfigurationError` naming the
failed condition.

What can be checked without metric knowledge (`m*'` and `c*'` are chosen by the user, the gains are known):
- (17) `m*'ᵀc*' ≠ 2` and (35) `m*'ᵀc*' < 2`; (27) `sign λ4 = sign λ5 = sign(2 − m*'ᵀc*')`; (28) `λ3, λ6 > 0`.
  The rotational block `A_ωω = −(2I + [c*']×[m*']×) Λ_ω` (32) is known too, so its spectrum is also checked
  numerically — Theorem 3.2's closed form assumes `m*' ∝ [0, 0, 1]` or `λ4 = λ5 = λ6`.
- (26) needs only `sign λ1 = sign λ2` from the gains; the sign of `2/z* − m*'ᵀq*'` needs the depth `z*` and the
  plane `q*'`. In the plane gauge through the control point (`ρ* = 0`) it is `1/z* > 0`, which is the paper's
  (34) assumption (control point near the dominant plane). So without `z*`, `q*'`: positive `λ1, λ2` are accepted
  under (34) and negative ones are refused (they are stable only when (34) fails, which cannot be verified).
- When `z_star` and `q_star` are given (simulation, analysis), (18) and (34) are checked and the whole linearised
  closed loop `L|₀ Λ` must be Hurwitz, for the DVS laws too.
- DVS laws (12)/(13): the proof covers `λ > 0` only, so every gain must be positive.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ddvs_service.control.interaction import L_bar_equilibrium, L_prime_equilibrium, closed_loop_matrix
from ddvs_service.lie import skew

F64 = NDArray[np.float64]

LAWS = ("dvs", "dvs_reduced", "ddvs")


class UnstableConfigurationError(ValueError):
    """A control configuration violates a stability or diffeomorphism condition of the paper."""


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise UnstableConfigurationError(message)


def check_configuration(
    law: str,
    gains: ArrayLike,
    m_star: ArrayLike,
    c_star: ArrayLike,
    q_star: ArrayLike | None = None,
    z_star: float | None = None,
) -> None:
    """Raise `UnstableConfigurationError` unless `law` with these 6 `gains` (1/s), control point `m_star`,
    `c_star` (normalised) and, when known, plane `q_star` (1/m) and depth `z_star` (m) is locally stable."""
    if law not in LAWS:
        raise ValueError(f"unknown control law {law!r}; expected one of {LAWS}")
    lam = np.asarray(gains, dtype=np.float64).reshape(6)
    m = np.asarray(m_star, dtype=np.float64).reshape(3)
    c = np.asarray(c_star, dtype=np.float64).reshape(3)
    if (q_star is None) != (z_star is None):
        raise ValueError("give both q_star and z_star (metric plane and depth of the control point) or neither")
    # The metric plane (q*' in 1/m, z* in m) when both are known.
    plane = None
    if q_star is not None and z_star is not None:
        plane = (np.asarray(q_star, dtype=np.float64).reshape(3), float(z_star))
    _require(bool(np.all(np.isfinite(lam)) and np.all(lam != 0.0)), f"gains must be finite and non-zero, got {lam}")
    if plane is not None:
        q, z = plane
        mq = float(m @ q)
        _require(abs(mq - 2.0 / z) > 1e-9, f"(18): m*'ᵀq*' must differ from 2/z* = {2.0 / z:.6g}, got {mq:.6g}")

    if law in ("dvs", "dvs_reduced"):
        _require(bool(np.all(lam > 0.0)), f"(12): the DVS law is proven stable for positive gains only, got {lam}")
        if plane is not None:
            q, z = plane
            _check_metric(L_prime_equilibrium(m, q, z), lam, m, q, z, "L'|₀ Λ (20)")
        return

    mc = float(m @ c)
    _require(abs(2.0 - mc) > 1e-9, f"(17): m*'ᵀc*' must differ from 2 (M is singular), got {mc:.6g}")
    if np.all(lam > 0.0):
        _require(mc < 2.0, f"(35): with positive gains m*'ᵀc*' must be < 2, got {mc:.6g}")
    _require(lam[2] > 0.0 and lam[5] > 0.0, f"(28): λ3 and λ6 must be positive, got λ3={lam[2]:g}, λ6={lam[5]:g}")
    _require(
        np.sign(lam[3]) == np.sign(lam[4]) == np.sign(2.0 - mc),
        f"(27): sign(λ4) = sign(λ5) = sign(2 − m*'ᵀc*') = {np.sign(2.0 - mc):+.0f} required, "
        f"got λ4={lam[3]:g}, λ5={lam[4]:g}",
    )
    a_ww = -(2.0 * np.eye(3) + skew(c) @ skew(m)) @ np.diag(lam[3:])
    _require(
        bool(np.all(np.linalg.eigvals(a_ww).real < 0.0)),
        f"(32): the rotational block A_ωω has eigenvalues {np.linalg.eigvals(a_ww)} (need negative real parts)",
    )
    _require(np.sign(lam[0]) == np.sign(lam[1]), f"(26): λ1 and λ2 must share a sign, got {lam[0]:g}, {lam[1]:g}")
    if plane is None:
        _require(
            lam[0] > 0.0,
            "(26): negative λ1, λ2 are stable only if 2/z* − m*'ᵀq*' < 0, which cannot be verified without the "
            "depth z_star and plane q_star; give them or use positive λ1, λ2 (stable under (34))",
        )
        return
    q, z = plane
    a = 2.0 / z - m @ q
    _require(
        np.sign(lam[0]) == np.sign(a),
        f"(26): sign(λ1) = sign(λ2) = sign(2/z* − m*'ᵀq*') = {np.sign(a):+.0f} required, got λ1={lam[0]:g}",
    )
    _check_metric(L_bar_equilibrium(m, q, z, c), lam, m, q, z, "L̄|₀ Λ (19)")


def _check_metric(L: F64, lam: F64, m: F64, q: F64, z: float, name: str) -> None:
    """(34) with known `q*'` (1/m) and `z*` (m), then the linearised closed loop must be Hurwitz."""
    mq = float(m @ q)
    if np.all(lam > 0.0):
        _require(z * mq < 2.0, f"(34): z* m*'ᵀq*' must be < 2 (control point near the plane), got {z * mq:.6g}")
    eig = np.linalg.eigvals(closed_loop_matrix(L, lam))
    _require(bool(np.all(eig.real < 0.0)), f"closed loop {name} is not Hurwitz: eigenvalues {eig}")
