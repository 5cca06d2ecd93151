"""Settings of the general registration of eq. (2) (`registration.general`), and the flags its results carry."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from ddvs_service.registration.config import RegistrationConfig
from ddvs_service.settings import Settings

Interpolation = Literal["keys", "bspline"]

FLAG_NO_PARALLAX = "no_parallax"  # parallax below detection: planar target or too little translation; ρ* := 0
FLAG_AMBIGUOUS = "ambiguous_parallax"  # a different parallax field fits almost as well
FLAG_LOW_TEXTURE = "low_texture"  # degenerate normal equations
FLAG_OCCLUSION = "occlusion"  # too few inliers / too little of the ROI visible
FLAG_LOST = "lost"  # no confident start: the global initialiser found none
FLAG_DIVERGED = "diverged"


InterpolationSetting = Annotated[Interpolation, Field(description=(
    "How the full-resolution steps of the general model sample the current image: bspline (the interpolating cubic "
    "B-spline; coarser levels keep Keys) or keys (Keys' cubic convolution)."))]
DEFAULT_INTERPOLATION: Interpolation = "bspline"
HoldEpipoleSetting = Annotated[float, Field(ge=0.0, le=100.0, description=(
    "Held epipole of the general model: a tracked frame whose warm start's parallax ρ* e is below this RMS (pixels) "
    "holds e at 0, freed when the frame's step on e is significant against the frame's noise or reaches twice it; "
    "0: e always free. Near the goal it halves the control error's noise on noisy, dimmed frames "
    "(results/robustness)."))]


class GeneralConfig(Settings):
    """Settings of the general registration (ranges and descriptions in each `Field`).

    - `base`: the planar engine's settings (pyramid, iterations, gain grid, robust loss, tolerances), shared.
    - `rho_degree`: 2 (biquadratic, 6 coefficients) or 3 (bicubic, 13).
    - `estimate_levels`: pyramid levels (finest first) on which ρ* is estimated from the planar solution.
    - `min_parallax_px`: RMS parallax displacement over the ROI below which ρ* is declared unobserved (set to 0).
    - `min_parallax_snr`: the parallax must also exceed this many standard errors.
    - `min_margin`: relative cost gap to a different parallax solution below which the result is flagged ambiguous.
    - `distinct_epipole_deg`: two solutions whose epipole directions differ by more than this are different.
    - `hold_epipole_px`: the held epipole (`general` module docstring), 0 = never held.
    - `interpolation`: how the full-resolution steps sample the current image, "bspline" (the interpolating cubic
      B-spline, `kernels.bspline`; coarser levels keep Keys) or "keys" (Keys' cubic convolution). Near the paper's
      equilibrium the warp must be right to ~0.002 px for the control error (16) to be within 1e-4; there Keys' own
      error dominates the residual. Worst error of (16) along the paper's trajectory, × the criterion's tolerance
      (benchmarks/general_accuracy.py): anti-aliased frames (texture blurred by 2 texels, 4×4 rays per pixel)
      0.80 with the B-spline vs 2.71 with Keys; frames with a 0.7 px optical blur 1.80 vs 5.0; point-sampled
      (aliased) frames 8.7 vs 13.3, but 1.05 vs 0.76 on their first 180 images. The B-spline's prefilter runs only over
      a window around the warped ROI (`spline_window`); it makes a tracking frame dearer than with Keys
      (docs/performance.md).
    """

    base: RegistrationConfig = Field(default_factory=RegistrationConfig, description=(
        "The planar engine's settings (pyramid, iterations, gain grid, robust loss, tolerances), shared."))
    rho_degree: Literal[2, 3] = Field(default=2, description="2 (biquadratic, 6 coefficients) or 3 (bicubic, 13).")
    estimate_levels: int = Field(default=2, ge=1, le=8, description=(
        "Pyramid levels (finest first) on which ρ* is estimated from the planar solution."))
    min_parallax_px: float = Field(default=0.05, ge=0.0, le=100.0, description=(
        "RMS parallax displacement over the ROI (pixels) below which ρ* is declared unobserved (set to 0)."))
    min_parallax_snr: float = Field(default=10.0, ge=0.0, le=1e6, description=(
        "The parallax must also exceed this many standard errors."))
    min_margin: float = Field(default=0.002, ge=0.0, le=1.0, description=(
        "Relative cost gap to a different parallax solution below which the result is flagged ambiguous."))
    distinct_epipole_deg: float = Field(default=20.0, gt=0.0, le=180.0, description=(
        "Two solutions whose epipole directions differ by more than this (degrees) are different."))
    interpolation: InterpolationSetting = DEFAULT_INTERPOLATION
    hold_epipole_px: HoldEpipoleSetting = 0.05
