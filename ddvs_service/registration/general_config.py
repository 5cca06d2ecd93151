"""Settings of the general registration of eq. (2) (`registration.general`), and the flags its results carry."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from ddvs_service.registration.config import RegistrationConfig

Interpolation = Literal["keys", "bspline"]

FLAG_NO_PARALLAX = "no_parallax"  # parallax below detection: planar target or too little translation; ρ* := 0
FLAG_AMBIGUOUS = "ambiguous_parallax"  # a different parallax field fits almost as well
FLAG_LOW_TEXTURE = "low_texture"  # degenerate normal equations
FLAG_OCCLUSION = "occlusion"  # too few inliers / too little of the ROI visible
FLAG_LOST = "lost"  # no confident start: the global initialiser found none
FLAG_DIVERGED = "diverged"


@dataclass(frozen=True)
class GeneralConfig:
    """Settings of the general registration.

    - `base`: the planar engine's settings (pyramid, iterations, gain grid, robust loss, tolerances), shared.
    - `rho_degree`: 2 (biquadratic, 6 coefficients) or 3 (bicubic, 13).
    - `estimate_levels`: pyramid levels (finest first) on which ρ* is estimated from the planar solution.
    - `min_parallax_px`: RMS parallax displacement over the ROI below which ρ* is declared unobserved (set to 0).
    - `min_parallax_snr`: the parallax must also exceed this many standard errors.
    - `min_margin`: relative cost gap to a different parallax solution below which the result is flagged ambiguous.
    - `distinct_epipole_deg`: two solutions whose epipole directions differ by more than this are different.
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

    base: RegistrationConfig = field(default_factory=RegistrationConfig)
    rho_degree: int = 2
    estimate_levels: int = 2
    min_parallax_px: float = 0.05
    min_parallax_snr: float = 10.0
    min_margin: float = 0.002
    distinct_epipole_deg: float = 20.0
    interpolation: Interpolation = "bspline"

    def __post_init__(self) -> None:
        if self.rho_degree not in (2, 3):
            raise ValueError(f"rho_degree must be 2 or 3, got {self.rho_degree}")
        if self.estimate_levels < 1:
            raise ValueError(f"estimate_levels must be ≥ 1, got {self.estimate_levels}")
        if not self.min_parallax_px >= 0.0 or not self.min_parallax_snr >= 0.0:
            raise ValueError("min_parallax_px and min_parallax_snr must be ≥ 0")
        if self.interpolation not in ("keys", "bspline"):
            raise ValueError(f"interpolation must be 'keys' or 'bspline', got {self.interpolation!r}")
