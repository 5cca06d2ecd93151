"""The general model's one-shot registration (`register_general`), started by the global initialiser when no start
is given. Kept apart from the engine (`registration.general`), which the initialiser itself uses for its step 5, so
that neither module imports the other."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ddvs_service.registration.general import GeneralRegistration, _State
from ddvs_service.registration.general_config import FLAG_LOST, GeneralConfig
from ddvs_service.registration.general_result import GeneralResult
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.images import checked_grey
from ddvs_service.registration.reacquisition import Reacquisition
from ddvs_service.registration.reference import Roi


def register_general(
    reference: ArrayLike,
    current: ArrayLike,
    roi: Roi | None = None,
    G0: ArrayLike | None = None,
    e0: ArrayLike | None = None,
    rho0: ArrayLike | None = None,
    config: GeneralConfig | None = None,
    mask: ArrayLike | None = None,
) -> GeneralResult:
    """One-shot general registration of `current` against `reference` over `roi = (x, y, w, h)` (reference pixels).

    Without `rho0` ρ* is estimated (several epipole starts, module docstring); `G0` is the starting homography
    (the global initialiser's when None). With `rho0` (coefficients of `ParallaxBasis`, this config's degree) ρ* is
    held fixed and only `G`, `e` (from `e0`, default 0), `S`, `β` are estimated from `G0` (required then).
    Raises ValueError on bad input; a failed registration is reported in the result (`converged`, `reason`, `flags`).
    """
    config = config or GeneralConfig()
    problem = GeneralRegistration.prepare(reference, roi=roi, mask=mask, config=config)
    cur = checked_grey(current, "current")
    if cur.shape != problem.planar.shape:
        raise ValueError(f"current image is {cur.shape[1]}×{cur.shape[0]}, expected the reference's "
                         f"{problem.planar.shape[1]}×{problem.planar.shape[0]}")
    start = None if G0 is None else np.asarray(G0, dtype=np.float64).reshape(3, 3)
    if rho0 is None:
        if start is None:
            start = Reacquisition(problem.planar, problem, GlobalInitConfig())(cur).G
            if start is None:
                return problem._failed(_State(np.eye(3), np.zeros(3), np.zeros(problem.basis.size),
                                              np.ones(problem.grid), 0.0, None),
                                       "global initialisation found no confident estimate (LOST)", [FLAG_LOST])
        return problem.estimate(cur, start)
    rho = np.asarray(rho0, dtype=np.float64).reshape(-1)
    if rho.size != problem.basis.size:
        raise ValueError(f"rho0 has {rho.size} coefficients, expected {problem.basis.size} "
                         f"(degree {config.rho_degree})")
    if start is None:
        raise ValueError("G0 is required with rho0 (tracking from a known parallax field)")
    e = np.zeros(3) if e0 is None else np.asarray(e0, dtype=np.float64).reshape(3)
    return problem.track(cur, start, e, rho)
