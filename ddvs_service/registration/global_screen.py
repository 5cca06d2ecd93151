"""Screening of the global initialiser's starting warps: a short planar refinement of all of them at once.

Every start is refined by robust ESM Gauss-Newton on the planar model (eqs. (4)–(5) with `ρ* ≡ 0`, one global gain
and a bias; `kernels/global_screen.py` builds the normal equations of all the starts in one launch per iteration)
on two pyramid levels: one level coarser than the search level, then the search level, at most `iterations` steps
per level. The update of each start is the planar engine's (`registration.planar`), `G ← G · N⁻¹ E(Σ xᵢ Aᵢ) N`
(`N` the level's normalisation `q = (p − c) / s` around the ROI centre), `a ← a + δa`, `b ← b + δb`, except that
the exponential is its degree-4 Taylor polynomial `E` (`retraction`, evaluated for all the starts at once; any
retraction leaves the Gauss-Newton fixed point where it is, and the warps are brought back to det 1 at the end); an
update
moving a ROI corner by more than `MAX_STEP_FRACTION` of the ROI size is scaled down; the robust scale
σ = 1.4826 · median |r| comes from the previous evaluation (the first one is plain least squares), never below
`SCALE_FLOOR` grey levels. A start stops at a level once the corner motion still to come
(`solver.remaining_motion`) is below `TOLERANCE_PX` level pixels, and for good when less than `MIN_VALID_RATIO` of
the ROI stays inside the current image, its first normal equations are degenerate, or an update is not finite: it
keeps its last warp (the photometric ranking that follows sorts it out).

Warps `G` map reference pixels to current pixels; the caller's are full-resolution pixels, det 1.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ddvs_service.lie import SL3_GENERATORS
from ddvs_service.registration.global_fourier_mellin import SearchPair, SearchReference, level_roi
from ddvs_service.registration.images import level_matrix
from ddvs_service.registration.planar import project
from ddvs_service.registration.reference import normalisation
from ddvs_service.registration.solver import DEGENERATE_RCOND, MAD_TO_SIGMA, remaining_motion
from kernels.backend import compile_settings
from kernels.exclusive import GATE
from kernels.global_screen import (
    FRAME_NORM,
    FRAME_ROI,
    GENERATORS,
    N_FRAME,
    N_GEOMETRIC,
    N_START,
    N_SUMS,
    N_TRIANGLE,
    N_UNKNOWNS,
    START_BIAS,
    START_G,
    START_GAIN,
    START_SIGMA,
    screen_step,
)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
TOLERANCE_PX = 0.05  # convergence: corner motion still to come, level pixels
MIN_VALID_RATIO = 0.2  # a start keeping less of the ROI inside the current image has diverged
MAX_STEP_FRACTION = 0.25  # largest corner motion of one update, fraction of the ROI size
SCALE_FLOOR = 0.5  # grey levels
_UPPER = np.triu_indices(N_UNKNOWNS)
_GENERATORS_FLAT = SL3_GENERATORS.reshape(N_GEOMETRIC, 9)
_EYE = np.eye(3)
if not np.array_equal(np.array(GENERATORS, dtype=np.float64).reshape(8, 3, 3), SL3_GENERATORS):
    raise AssertionError("kernels.global_screen.GENERATORS and lie.SL3_GENERATORS disagree")


@dataclass(frozen=True)
class _Level:
    """One screening level: absolute pyramid `index`, `D` (full-resolution → level pixels), the normalisation `N`,
    the ROI corners (homogeneous, 3×4), its size and pixel count, and the kernel's `frame` array."""

    index: int
    D: F64
    D_inv: F64
    N: F64
    N_inv: F64
    corners: F64
    size: float
    n_pixels: int
    frame: F32

    @staticmethod
    def build(roi: tuple[int, int, int, int], index: int) -> _Level:
        u0, v0, w, h = level_roi(roi, index)
        u1, v1 = u0 + w - 1, v0 + h - 1
        norm, N = normalisation((u0, v0, u1, v1))
        frame = np.zeros(N_FRAME, np.float32)
        frame[FRAME_ROI : FRAME_ROI + 4] = (u0, v0, u1, v1)
        frame[FRAME_NORM : FRAME_NORM + 3] = norm
        D = level_matrix(index)
        corners = np.array([[u0, u1, u1, u0], [v0, v0, v1, v1], [1.0, 1.0, 1.0, 1.0]])
        D_inv = np.asarray(np.linalg.inv(D), dtype=np.float64)
        N_inv = np.asarray(np.linalg.inv(N), dtype=np.float64)
        return _Level(index, D, D_inv, N, N_inv, corners, float(max(u1 - u0, v1 - v0)), w * h, frame)


def retraction(x: F64) -> F64:
    """`E(X) = I + X + X²/2 + X³/6 + X⁴/24` for `X = Σ xᵢ Aᵢ` of each row of `x` (K, 8): a stack (K, 3, 3) that
    agrees with `exp(X)` to fourth order (first omitted term `X⁵/120`: ≈ 3e-4 at ‖X‖ = 0.5)."""
    X = (x @ _GENERATORS_FLAT).reshape(-1, 3, 3)
    E = np.broadcast_to(_EYE, X.shape).copy()
    term = E.copy()
    for k in range(1, 5):
        term = term @ X / k
        E += term
    return E


def _degenerate(H: F64) -> NDArray[np.bool_]:
    """Per normal matrix of the stack `H` (K, n, n): a non-positive diagonal or a reciprocal condition number of the
    diagonally scaled matrix below `DEGENERATE_RCOND` (the planar engine's test)."""
    d = np.diagonal(H, axis1=1, axis2=2)
    bad = ~np.all(d > 0, axis=1)
    scale = np.sqrt(np.where(d > 0, d, 1.0))
    eig = np.linalg.eigvalsh(H / (scale[:, :, None] * scale[:, None, :]))
    return bad | ~(eig[:, 0] > DEGENERATE_RCOND * eig[:, -1])


def _solve(H: F64, b: F64) -> F64:
    """Solutions of the stack of systems `H x = b` ((K, n, n), (K, n)); NaN rows for the singular ones."""
    try:
        return np.asarray(np.linalg.solve(H, b[:, :, None])[:, :, 0], dtype=np.float64)
    except np.linalg.LinAlgError:  # one singular matrix fails the whole stack: solve them one by one
        out = np.full(b.shape, np.nan)
        for k in range(len(H)):
            with contextlib.suppress(np.linalg.LinAlgError):
                out[k] = np.linalg.solve(H[k], b[k])
        return out


class BatchScreen:
    """The reference side of the screening, prepared once per (reference, ROI): the two levels' geometry and
    buffers. `run` screens a list of starts against one current image."""

    def __init__(self, reference: SearchReference, full_roi: tuple[int, int, int, int], iterations: int) -> None:
        self.reference = reference
        self.iterations = iterations
        self.levels = (_Level.build(full_roi, reference.level + 1), _Level.build(full_roi, reference.level))

    def run(self, search: SearchPair, starts: list[F64]) -> list[F64]:
        """Screened full-resolution warps (det 1) of the full-resolution `starts`, in the same order."""
        if not starts:
            return []
        K = len(starts)
        G = np.stack(starts).astype(np.float64)
        params = np.zeros((K, N_START), np.float32)
        params[:, START_GAIN] = 1.0
        failed = np.zeros(K, bool)
        images = ((self.reference.coarse, search.coarse), (self.reference.image, search.current))
        for level, (ref, cur) in zip(self.levels, images, strict=True):
            G_l = level.D @ G @ level.D_inv
            self._solve_level(level, ref, cur, G_l, params, failed)
            G = level.D_inv @ G_l @ level.D
        return [g / np.cbrt(np.linalg.det(g)) for g in G]

    def _solve_level(self, level: _Level, ref: F32, cur: F32, G_l: F64, params: F32, failed: NDArray[np.bool_]
                     ) -> None:
        """Gauss-Newton on one level for every start not yet `failed`; updates `G_l` (level pixels) and `params`
        (gain, bias, σ) in place and marks the starts that fail."""
        K = len(G_l)
        active = ~failed
        steps: list[list[float]] = [[] for _ in range(K)]
        out = np.empty((K, N_SUMS + level.n_pixels), np.float32)
        limit = MAX_STEP_FRACTION * level.size
        for it in range(self.iterations):
            idx = np.flatnonzero(active)
            if idx.size == 0:
                break
            params[idx, START_G : START_G + 9] = G_l[idx].reshape(-1, 9)
            batch = np.ascontiguousarray(params[idx])
            GATE.checkpoint()  # a frame waiting for Taichi goes first (`kernels.exclusive`)
            with compile_settings():  # its first call compiles it (`kernels.backend.compile_settings`)
                screen_step(ref, cur, batch, level.frame, out[: idx.size])
            GATE.checkpoint()  # and again before the numpy work on the sums (`kernels.exclusive`)
            acc = out[: idx.size, :N_SUMS].astype(np.float64)
            n_valid = acc[:, N_TRIANGLE + N_UNKNOWNS]
            H = np.zeros((idx.size, N_UNKNOWNS, N_UNKNOWNS))
            H[:, _UPPER[0], _UPPER[1]] = acc[:, :N_TRIANGLE]
            H = H + np.triu(H, 1).transpose(0, 2, 1)
            g = acc[:, N_TRIANGLE : N_TRIANGLE + N_UNKNOWNS]
            stop = n_valid < MIN_VALID_RATIO * level.n_pixels
            if it == 0:
                stop |= _degenerate(H)
            ordered = np.sort(out[: idx.size, N_SUMS:], axis=1)  # invalid pixels (−1) first
            n_invalid = level.n_pixels - n_valid.astype(int)
            middle = np.clip(n_invalid + np.maximum(n_valid.astype(int) - 1, 0) // 2, 0, level.n_pixels - 1)
            sigma = np.maximum(MAD_TO_SIGMA * ordered[np.arange(idx.size), middle], SCALE_FLOOR)
            solvable = ~stop
            delta = np.full((idx.size, N_UNKNOWNS), np.nan)
            if solvable.any():
                delta[solvable] = _solve(H[solvable], -g[solvable])
            stop |= ~np.all(np.isfinite(delta), axis=1)
            delta[stop] = 0.0
            G_old = G_l[idx]
            before = project(G_old, level.corners)
            G_new = G_old @ level.N_inv @ retraction(delta[:, :N_GEOMETRIC]) @ level.N
            step = np.max(np.abs(project(G_new, level.corners) - before), axis=(1, 2))
            big = ~(step <= limit)  # also catches NaN
            if big.any():
                delta[big] *= np.where(np.isfinite(step[big]), limit / step[big], 0.0)[:, None]
                G_new[big] = G_old[big] @ level.N_inv @ retraction(delta[big, :N_GEOMETRIC]) @ level.N
            keep = idx[~stop]
            failed[idx[stop]] = True
            active[idx[stop]] = False
            G_l[keep] = G_new[~stop]
            params[keep, START_GAIN] += delta[~stop, N_GEOMETRIC]
            params[keep, START_BIAS] += delta[~stop, N_GEOMETRIC + 1]
            params[keep, START_SIGMA] = sigma[~stop]
            for k, moved in zip(keep, step[~stop], strict=True):
                steps[k].append(float(moved))
                if remaining_motion(steps[k]) < TOLERANCE_PX:
                    active[k] = False
