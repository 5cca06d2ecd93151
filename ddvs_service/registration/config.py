"""Settings of the planar direct registration (eq. (5)); validated on construction."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

RobustLoss = Literal["huber", "tukey", "none"]
ROBUST_CODES: dict[str, int] = {"none": 0, "huber": 1, "tukey": 2}
MAX_GAIN_NODES_PER_AXIS = 4
MIN_GAMMA, MAX_GAMMA = 0.2, 5.0  # camera response exponents accepted
MAX_DEFOCUS_PX = 16.0  # largest relative defocus radius accepted (full-resolution pixels)
PIXELS_PER_BAND = 16384  # ROI pixels per row band of a step kernel's reduction (see `bands`)


@dataclass(frozen=True)
class RegistrationConfig:
    """How `register` and `Tracker` minimise eq. (5).

    - `levels`: pyramid levels at most (1 = full resolution only); fewer are used when the ROI would shrink below
      `min_level_size` pixels on a side. The default (8) lets the ROI size choose: a 200×150 ROI gets 4 levels
      (coarsest 25×18 px), enough for 40 px + 20° + 15 % scale from identity.
    - `max_iterations`: Gauss-Newton iterations per level.
    - `gain_grid`: (rows, cols) of the bilinear gain surface S of eq. (4) over the ROI; (1, 1) = one global gain.
    - `gain_range`: (lowest, highest) value of a gain node of S. `S · I + β` maps the current frame's grey levels
      (or irradiance) to the reference's, so a physical camera's gain is positive; the solver projects every update
      of the nodes onto this range (`solver.bounded_gains`). Without the bound a node under an occluder on a dimmed
      scene went negative (issue 20, README "Robustness"), the surface absorbing the foreign object with an
      inverted image. 0.02 … 50: a frame 50× brighter or darker than the reference (an 8-bit frame 50× darker
      keeps 5 grey levels of the target); γ 2.2 raises an encoded ratio to the power 2.2 (3.5× darker: 16).
    - `robust`: M-estimator (Huber k = 1.345 σ, Tukey c = 4.685 σ, or plain least squares); σ = 1.4826 · median |r|,
      never below `scale_floor` grey levels.
    - `min_inlier_ratio`: fraction of the ROI's pixels with |r| ≤ 4.685 σ required to call the result converged.
    - `min_valid_ratio`: fraction of the ROI that must stay inside the current image, else the estimate diverged.
    - `step_tolerance_px`: convergence when the ROI corners are within this many full-resolution pixels of the
      fixed point at the finest level: the planar engine bounds the motion still to come by the geometric tail of
      its last steps (`solver.remaining_motion`, the Gauss-Newton skeleton of both engines);
      `coarse_step_tolerance_px`: the same, in level pixels, on the coarser levels (which only need to bring the
      finer level into its basin).
    - `tracking_step_tolerance_px`: `step_tolerance_px` for the `Tracker`'s warm-started frames. A stream refines
      its estimate again on every frame, and on consecutive frames (2 px apart, benchmarks/bench_registration.py)
      the worst corner error is the same 0.032 px at 1e-3 and at 1e-2 px (the floor is interpolation, not
      convergence) while the iterations per frame fall from 3.0 to 1.5.
    - `tracking_levels`: pyramid levels the `Tracker` uses from a warm start (consecutive frames move little); it
      retries with every level when that does not converge (at most `levels` are used).
    - `tracking_give_up_iterations`: the iterations after which the `Tracker`'s attempts give up on a level that
      has not converged: a coarse one, or the finest while its inlier ratio is below `min_inlier_ratio`
      (`solver.gauss_newton`'s `give_up_below`). A frame within reach converges at a coarse level in a few (the
      retry over the pyramid after a 3° / 1 cm jump: 2–5) and keeps its support at the finest (the warm starts of
      the robustness runs: above 0.56 after the first step, up to 23 iterations under noise), so the frame that
      discovers a loss (the target hidden or out of reach) costs about twice this many iterations, not
      `max_iterations` at every level of both attempts.
    - `predict_motion`: the `Tracker` starts a frame from the constant-velocity extrapolation of the last two good
      estimates (falling back to the last estimate when that fails); off: from the last estimate.
    - `max_step_fraction`: an update moving a corner by more than this fraction of the ROI size is scaled down.
    - `gamma`: the camera's response exponent. The engine compares irradiance `255 (I / 255)^γ`, not the encoded
      grey levels `I` (1 = as they are; ≈ 2.2 for sRGB-like cameras): defocus blurs irradiance, and compared in
      encoded levels a sharp reference and a defocused current image disagree around bright structure, which moves
      the optimum (bikes 1→6, 200×150 ROI: 2.46 px from the ground truth with the defaults, 0.57 px with γ = 2.2
      and the defocus estimated; `benchmarks/real_pairs.py`, `benchmarks/irradiance_blur.py`). `S`, `β`,
      residuals and σ are then in irradiance units. On strongly darkened frames γ > 1 leaves few irradiance levels
      (leuven 1→6 at 200×150: 1.00 → 1.28 px). Cost: one in-place launch per frame (docs/performance.md).
    - `defocus_px`: the current frames' defocus relative to the reference, the radius (full-resolution pixels) of
      the uniform disk that blurs the reference's irradiance before its pyramid is built; 0 = none.
      `registration.defocus.register_defocus` estimates it for a pair. Cost: one disk blur per reference, growing
      with the radius (docs/performance.md).
    - `bands`: the most row bands of the reduction (parallel work items), 1…32; a level uses one band per
      `PIXELS_PER_BAND` ROI pixels (`bands_for`): on small ROIs handing bands to threads costs more than it saves
      (docs/performance.md).
    """

    levels: int = 8
    max_iterations: int = 30
    gain_grid: tuple[int, int] = (1, 1)
    gain_range: tuple[float, float] = (0.02, 50.0)
    robust: RobustLoss = "huber"
    min_inlier_ratio: float = 0.5
    min_valid_ratio: float = 0.3
    step_tolerance_px: float = 1e-3
    coarse_step_tolerance_px: float = 0.05
    tracking_step_tolerance_px: float = 1e-2
    tracking_levels: int = 1
    tracking_give_up_iterations: int = 10
    predict_motion: bool = True
    max_step_fraction: float = 0.25
    scale_floor: float = 0.5
    min_level_size: int = 16
    bands: int = 8
    gamma: float = 1.0
    defocus_px: float = 0.0

    def bands_for(self, n_pixels: int) -> int:
        """Row bands for a level of `n_pixels` ROI pixels: one per `PIXELS_PER_BAND`, between 1 and `bands`."""
        return max(1, min(self.bands, -(-n_pixels // PIXELS_PER_BAND)))

    def __post_init__(self) -> None:
        if not 1 <= self.levels <= 8:
            raise ValueError(f"levels must be in 1..8, got {self.levels}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be ≥ 1, got {self.max_iterations}")
        rows, cols = self.gain_grid
        if not (1 <= rows <= MAX_GAIN_NODES_PER_AXIS and 1 <= cols <= MAX_GAIN_NODES_PER_AXIS):
            raise ValueError(
                f"gain_grid must be (rows, cols) with each in 1..{MAX_GAIN_NODES_PER_AXIS}, got {rows}×{cols}"
            )
        low, high = self.gain_range
        if not 0.0 < low < high < float("inf"):
            raise ValueError(f"gain_range must be (low, high) with 0 < low < high < inf, got {self.gain_range}")
        if self.robust not in ROBUST_CODES:
            raise ValueError(f"robust must be one of {sorted(ROBUST_CODES)}, got {self.robust!r}")
        for name in ("min_inlier_ratio", "min_valid_ratio", "max_step_fraction"):
            value = getattr(self, name)
            if not 0.0 < value <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {value}")
        for name in ("step_tolerance_px", "coarse_step_tolerance_px", "tracking_step_tolerance_px"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.tracking_levels < 1:
            raise ValueError(f"tracking_levels must be ≥ 1, got {self.tracking_levels}")
        if self.tracking_give_up_iterations < 1:
            raise ValueError(f"tracking_give_up_iterations must be ≥ 1, got {self.tracking_give_up_iterations}")
        if not self.scale_floor > 0.0:
            raise ValueError(f"scale_floor must be > 0 grey levels, got {self.scale_floor}")
        if self.min_level_size < 8:
            raise ValueError(f"min_level_size must be ≥ 8 pixels, got {self.min_level_size}")
        if not MIN_GAMMA <= self.gamma <= MAX_GAMMA:
            raise ValueError(f"gamma must be in {MIN_GAMMA}..{MAX_GAMMA}, got {self.gamma}")
        if not 0.0 <= self.defocus_px <= MAX_DEFOCUS_PX:
            raise ValueError(f"defocus_px must be in 0..{MAX_DEFOCUS_PX} pixels, got {self.defocus_px}")
        if not 1 <= self.bands <= 32:
            raise ValueError(f"bands must be in 1..32, got {self.bands}")
