"""Accuracy of the general registration along the paper's synthetic trajectory (saddle, 200×150 ROI), measured as
`tests/test_general_registration.py::test_paper_trajectory_from_a_cold_start` does (cold start on image 0, then
the same images tracked), for several ways of forming the frames: the warp's RMS error against the true warp over
the ROI (px), the error of the control error (16) from the estimate, absolute and relative to the criterion's
tolerance max(1 % of its norm, 1e-4), and the shape error of the estimated ρ* (`rho_shape_error`).

Renders: `point` (`sim.freeflyer.render_view`: one ray per pixel centre), `box:K` (`render_camera` with K×K rays per
pixel averaged, no optical blur), `camera:S` (`render_camera`, 4×4 rays per pixel, Gaussian optical blur of S px)
and `texture:S` (as `box:4`, the texture blurred by a Gaussian of S texels: a blur carried by the surface, the same
in every frame once warped, where the optical blur of `camera:S` is the same in every *image* and so differs between
two frames by the warp's local distortion); a `/bspline` suffix registers with `GeneralConfig(interpolation="bspline")`
(Keys by default).

The benchmark `benchmarks/general_accuracy.py` prints these figures for several renders.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from ddvs_service.camera import Intrinsics
from ddvs_service.control.law import ControlConfig, ControlLaw
from ddvs_service.lie import pose
from ddvs_service.registration.general import GeneralRegistration
from ddvs_service.registration.general_basis import ParallaxBasis
from ddvs_service.registration.general_config import GeneralConfig
from ddvs_service.registration.general_result import GeneralResult
from ddvs_service.registration.general_tracker import GeneralTracker
from ddvs_service.registration.global_init import GlobalInitConfig
from ddvs_service.registration.reacquisition import Reacquisition
from orchestration.experiment_synthetic import run_synthetic
from sim.freeflyer import render_camera, render_view
from sim.ground_truth import ground_truth, parallax_map
from sim.surfaces import paper_saddle

INTR = Intrinsics.centred(500.0, 550, 418)
ROI = (175, 134, 200, 150)
CONTROL_POINT = (INTR.cx, INTR.cy)


def renderer(spec: str, texture: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """The frame of the saddle seen from a pose (4×4) for a render spec of the module docstring."""
    saddle = paper_saddle()
    kind, _, value = spec.split("/")[0].partition(":")
    if kind == "point":
        return lambda T: render_view(saddle, texture, INTR, T)[0]
    if kind == "box":
        return lambda T: render_camera(saddle, texture, INTR, T, psf_sigma=0.0, oversample=int(value))
    if kind == "camera":
        return lambda T: render_camera(saddle, texture, INTR, T, psf_sigma=float(value))
    if kind == "texture":
        blurred = np.asarray(cv2.GaussianBlur(texture, (0, 0), float(value)), np.float32)
        return lambda T: render_camera(saddle, blurred, INTR, T, psf_sigma=0.0)
    raise ValueError(f"unknown render {spec!r}: point, box:K, camera:SIGMA or texture:SIGMA")


def rho_shape_error(basis: ParallaxBasis, coeffs: np.ndarray, p: np.ndarray, rho: np.ndarray) -> float:
    """Relative error of the *shape* of the ρ* coefficients `coeffs` against the true parallax `rho` (ρ* of the
    ground truth, reference plane Z = 1) at the reference pixels `p` (the ROI's, N × 2): the true ρ* is fitted by
    least squares with a plane `aᵀ(u, v, 1)` plus the basis (the plane is the gauge the basis removes, module
    docstring of `general_basis`), and `coeffs` is compared with its basis part after the best scale `λ` (the scale
    gauge `(e, ρ*) ~ (s e, ρ*/s)`, sign included): `‖λ coeffs − c_true‖ / ‖c_true‖`. Independent of both gauges; the
    basis is orthonormal over the ROI, so it is also the relative RMS error of ρ* over the ROI."""
    phi = basis.values(p)
    fit = np.linalg.lstsq(np.c_[p, np.ones(len(p)), phi], rho, rcond=None)[0]
    truth = fit[3:]
    scale = float(truth @ coeffs) / max(float(coeffs @ coeffs), 1e-300)
    return float(np.linalg.norm(scale * coeffs - truth) / np.linalg.norm(truth))


@dataclass
class Run:
    """One tracked trajectory: per image the figures of `measure`, the tracker after the last image, its result."""

    rows: list[dict[str, float]]
    tracker: GeneralTracker
    last: GeneralResult


def measure(render: Callable[[np.ndarray], np.ndarray], config: GeneralConfig) -> Run:
    """Cold start on the frame `render(I₄)`, then the images of the exact-geometry decoupled run (every 2nd of the
    first 20, every 10th, the last) tracked with `config`; per image: index, |ε̄|, warp RMS error (px), |Δε̄|,
    |Δε̄| / tolerance, converged, the ρ* shape error (`rho_shape_error`)."""
    saddle = paper_saddle()
    trajectory = run_synthetic("ddvs")
    law = ControlLaw(ControlConfig(law="ddvs", gains=0.4, stop_threshold=1e-3), INTR)
    x, y, w, h = ROI
    u, v = np.meshgrid(np.arange(x, x + w, dtype=float), np.arange(y, y + h, dtype=float))
    p = np.c_[u.ravel(), v.ravel()]
    rho = parallax_map(saddle, INTR, np.eye(4))[p[:, 1].astype(int), p[:, 0].astype(int)]
    engine = GeneralRegistration.prepare(render(np.eye(4)), ROI, config=config)
    tracker = GeneralTracker(engine)
    rows = []
    for k in [*range(0, 20, 2), *range(20, trajectory.images, 10), trajectory.images - 1]:
        T = pose(trajectory.rotations[k], trajectory.positions[k])
        image = render(T)
        if k == 0:  # the cold start: from the global initialiser's estimate, ρ* estimated on this frame
            start = Reacquisition(engine.planar, engine, GlobalInitConfig())(image)
            if start.G is None:
                raise RuntimeError(f"the global initialiser found no start on the first frame: {start.reason}")
            tracker.reset(start.G)
        result = tracker.track(image)
        gt = ground_truth(saddle, INTR, np.eye(4), T)
        P = np.c_[p, np.ones(len(p))] @ gt.G.T + np.outer(rho, gt.e)
        warp = float(np.sqrt(np.mean(np.sum((result.warp(p) - P[:, :2] / P[:, 2:]) ** 2, axis=1))))
        exact = law.error(gt.G, gt.e, gt.rho)
        err = float(np.linalg.norm(law.error(result.G, result.e, result.rho_at(CONTROL_POINT)) - exact))
        norm = float(np.linalg.norm(exact))
        rows.append({"image": k, "norm": norm, "warp_px": warp, "error": err,
                     "relative": err / max(0.01 * norm, 1e-4), "converged": bool(result.converged),
                     "rho_shape": rho_shape_error(tracker.basis, result.rho_coeffs, p, rho)})
    return Run(rows, tracker, result)
