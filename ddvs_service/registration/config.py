"""Settings of the planar direct registration (eq. (5)): the one definition of each engine setting, its default and
its range, validated on construction (pydantic). The service's `registration` settings extend this model
(`service.config.RegistrationSettings`), so an engine setting means the same and defaults the same everywhere.
"""

from __future__ import annotations

from typing import Annotated, Literal, Self

from pydantic import Field, model_validator

from ddvs_service.settings import Settings

RobustLoss = Literal["huber", "tukey", "none"]
ROBUST_CODES: dict[str, int] = {"none": 0, "huber": 1, "tukey": 2}
MAX_GAIN_NODES_PER_AXIS = 4
MIN_GAMMA, MAX_GAMMA = 0.2, 5.0  # camera response exponents accepted
MAX_DEFOCUS_PX = 16.0  # largest relative defocus radius accepted (full-resolution pixels)
PIXELS_PER_BAND = 16384  # ROI pixels per row band of a step kernel's reduction (see `bands`)
MAX_ITERATIONS = 200  # Gauss-Newton iterations per level accepted: a bound on one frame's work
GainNodes = Annotated[int, Field(ge=1, le=MAX_GAIN_NODES_PER_AXIS)]
GainBound = Annotated[float, Field(gt=0.0, le=1000.0)]


class RegistrationConfig(Settings):
    """How `register` and `Tracker` minimise eq. (5). Each field's description and range is in its `Field`; what
    they mean in more depth, and the reasons behind the defaults:

    - `levels`: pyramid levels at most (1 = full resolution only); fewer are used when the ROI would shrink below
      `min_level_size` pixels on a side. The default (8) lets the ROI size choose: a 200×150 ROI gets 4 levels
      (coarsest 25×18 px), enough for 40 px + 20° + 15 % scale from identity.
    - `gain_grid`: (rows, cols) of the bilinear gain surface S of eq. (4) over the ROI; (1, 1) = one global gain.
      The default 3×3 comes from the robustness matrix (README "Robustness"): a single gain cannot represent a
      light ramp, and it leaves the servo farther from the goal at the stop even on clean frames.
    - `gain_range`: (lowest, highest) value of a gain node of S. `S · I + β` maps the current frame's grey levels
      (or irradiance) to the reference's, so a physical camera's gain is positive; the solver projects every update
      of the nodes onto this range (`solver.bounded_gains`). Without the bound a node under an occluder on a dimmed
      scene went negative (README "Robustness"), the surface absorbing the foreign object with an
      inverted image. 0.02 … 50: a frame 50× brighter or darker than the reference (an 8-bit frame 50× darker
      keeps 5 grey levels of the target); γ 2.2 raises an encoded ratio to the power 2.2 (3.5× darker: 16).
    - `robust`: M-estimator (Huber k = 1.345 σ, Tukey c = 4.685 σ, or plain least squares); σ = 1.4826 · median |r|,
      never below `scale_floor` grey levels. The default Tukey (robustness matrix): its zero weight beyond 4.685 σ
      keeps an occluder out of the fit; Huber's bounded weight lets it drag the fit until the servo is LOST.
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

    levels: int = Field(default=8, ge=1, le=8, description=(
        "Pyramid levels at most (1 = full resolution only); fewer are used when the ROI would shrink below "
        "`min_level_size` pixels on a side."))
    max_iterations: int = Field(default=30, ge=1, le=MAX_ITERATIONS, description=(
        "Gauss-Newton iterations per pyramid level."))
    gain_grid: tuple[GainNodes, GainNodes] = Field(default=(3, 3), description=(
        "(rows, cols) of the bilinear gain surface S of eq. (4) over the ROI, each 1 to 4; (1, 1) = one global "
        "gain."))
    gain_range: tuple[GainBound, GainBound] = Field(default=(0.02, 50.0), description=(
        "(lowest, highest) value of a gain node of S, 0 < lowest < highest ≤ 1000: every update of the nodes is "
        "projected onto this range."))
    robust: RobustLoss = Field(default="tukey", description=(
        "M-estimator of eq. (5): huber (k = 1.345 σ), tukey (c = 4.685 σ) or none (plain least squares)."))
    min_inlier_ratio: float = Field(default=0.5, gt=0.0, le=1.0, description=(
        "Fraction of the ROI's pixels with |r| ≤ 4.685 σ required to call the result converged."))
    min_valid_ratio: float = Field(default=0.3, gt=0.0, le=1.0, description=(
        "Fraction of the ROI that must stay inside the current image, else the estimate diverged."))
    step_tolerance_px: float = Field(default=1e-3, gt=0.0, le=1.0, description=(
        "Convergence at the finest level: the ROI corners within this many full-resolution pixels of the fixed "
        "point."))
    coarse_step_tolerance_px: float = Field(default=0.05, gt=0.0, le=1.0, description=(
        "The same on the coarser levels, in level pixels."))
    tracking_step_tolerance_px: float = Field(default=1e-2, gt=0.0, le=1.0, description=(
        "`step_tolerance_px` for the tracker's warm-started frames."))
    tracking_levels: int = Field(default=1, ge=1, le=8, description=(
        "Pyramid levels the tracker uses from a warm start; it retries with every level when that does not "
        "converge."))
    tracking_give_up_iterations: int = Field(default=10, ge=1, le=MAX_ITERATIONS, description=(
        "Iterations after which the tracker gives up on a level that has not converged."))
    predict_motion: bool = Field(default=True, description=(
        "Start a tracked frame from the constant-velocity extrapolation of the last two good estimates."))
    max_step_fraction: float = Field(default=0.25, gt=0.0, le=1.0, description=(
        "An update moving a corner by more than this fraction of the ROI size is scaled down."))
    scale_floor: float = Field(default=0.5, gt=0.0, le=255.0, description=(
        "Lowest robust scale σ, grey levels."))
    min_level_size: int = Field(default=16, ge=8, le=1024, description=(
        "Smallest side of the ROI at a pyramid level, pixels."))
    bands: int = Field(default=8, ge=1, le=32, description=(
        "Most row bands of a step kernel's reduction (parallel work items); a level uses one per "
        f"{PIXELS_PER_BAND} ROI pixels."))
    gamma: float = Field(default=1.0, ge=MIN_GAMMA, le=MAX_GAMMA, description=(
        "The camera's response exponent: the engine compares irradiance 255 (I / 255)^γ (1 = grey levels as they "
        "are; about 2.2 for sRGB-like cameras)."))
    defocus_px: float = Field(default=0.0, ge=0.0, le=MAX_DEFOCUS_PX, description=(
        "Defocus of the current frames relative to the reference: radius (full-resolution pixels) of the uniform "
        "disk that blurs the reference's irradiance; 0 = none."))

    @model_validator(mode="after")
    def _gain_range_ordered(self) -> Self:
        low, high = self.gain_range
        if not low < high:
            raise ValueError(f"gain_range must be (low, high) with 0 < low < high, got {self.gain_range}")
        return self

    def bands_for(self, n_pixels: int) -> int:
        """Row bands for a level of `n_pixels` ROI pixels: one per `PIXELS_PER_BAND`, between 1 and `bands`."""
        return max(1, min(self.bands, -(-n_pixels // PIXELS_PER_BAND)))
