"""Cubic B-spline interpolation coefficients of a grey image (M. Unser, "Splines: a perfect fit for signal and image
processing", IEEE Signal Processing Magazine 16(6), 1999).

`coefficients(image, out)` fills `out` with the `c` such that `Σ_k c[k] β³(x − k)` (β³ the centred cubic B-spline,
separable in rows and columns) passes through every pixel value; `kernels.general_step.cubic_sample` with
`spline=True` samples that interpolant. Its frequency response stays flat much closer to the Nyquist frequency than
Keys' cubic convolution, which matters for sub-pixel registration (`kernels.general_step` module docstring).

The inverse of the sampled B-spline filter `(z + 4 + z⁻¹)/6` is separable and factors into a causal and an
anticausal first-order recursion with the pole `z = √3 − 2`; along each row, then along each column:
`c⁺[0] = Σ_{k < HORIZON} z^k s[k]`, `c⁺[i] = s[i] + z c⁺[i−1]`, `c⁻[n−1] = z/(z² − 1) (c⁺[n−1] + z c⁺[n−2])`,
`c⁻[i] = z (c⁻[i+1] − c⁺[i])`, `c = 6 c⁻` (mirror boundary; the truncated causal start is exact to `|z|^HORIZON`).
Float32; one launch: `LANES` rows per thread in parallel, then `LANES` columns per thread.

A window `(r0, r1, c0, c1)` (half-open rows and columns) filters only that rectangle, as if it were the whole image
(mirror boundary at its edges) and leaves `out` elsewhere untouched. Both recursions forget their start as `|z|^k`,
so inside the window, `HORIZON` or more samples away from every window edge that is not an image edge, the
coefficients equal the whole image's to float32 resolution (`window_for` sizes a window that way).
"""

import math

import numpy as np
import taichi as ti
from numpy.typing import NDArray

from kernels.backend import compile_settings

POLE = math.sqrt(3.0) - 2.0
HORIZON = 12  # |z|^12 = 1.4e-7: the causal start's truncation, below float32 resolution
LANES = 8  # lines filtered together by one thread: independent recursions, so that their latencies overlap


@ti.func
def _load(a: ti.template(), lines: ti.template(), i: ti.i32, along_rows: ti.template()):
    """Sample `i` of each of the `LANES` lines `lines` of `a` (rows when `along_rows`, else columns), as a vector:
    one call per step, not one per lane (each call is a tree Taichi's front end walks at every start)."""
    values = ti.Vector.zero(ti.f32, LANES)
    if ti.static(along_rows):
        values = ti.Vector([a[lines[j], i] for j in ti.static(range(LANES))])
    else:
        values = ti.Vector([a[i, lines[j]] for j in ti.static(range(LANES))])
    return values


@ti.func
def _store(a: ti.template(), lines: ti.template(), i: ti.i32, along_rows: ti.template(), values: ti.template()):
    """`a` at sample `i` of each of the `LANES` lines `lines` ← `values` (as `_load`)."""
    for j in ti.static(range(LANES)):
        if ti.static(along_rows):
            a[lines[j], i] = values[j]
        else:
            a[i, lines[j]] = values[j]


@ti.func
def _lines(src: ti.template(), dst: ti.template(), first: ti.i32, n: ti.i32, last_line: ti.i32,
           along_rows: ti.template(), gain: ti.template(), o: ti.i32):
    """Filter the `LANES` lines `first …` (rows when `along_rows`, else columns) over the `n` samples `o … o + n − 1`
    from `src` into `dst` (which may be `src`): `dst = gain · c⁻` (module docstring). Lanes past `last_line` repeat
    it: every step loads all lanes before it stores any, so a repeated line computes and stores the same values as
    its owner. Each recursion is a `while` loop that tests for its end between a step's stores and its loads, not at
    the loop's end: LLVM does not unroll such a loop (a `for` loop with a run-time count it unrolls several times
    over, plus a remainder copy), so its machine code holds one step; every start pays for that machine code when it
    loads the cached kernel."""
    z = ti.static(POLE)
    lines = ti.Vector([ti.min(first + j, last_line) for j in ti.static(range(LANES))])
    causal = ti.Vector.zero(ti.f32, LANES)
    zk = 1.0
    for k in range(HORIZON):
        causal += zk * _load(src, lines, o + k, along_rows)
        zk *= z
    i = 0
    while True:  # step i stores c⁺[i] and loads s[i + 1]
        _store(dst, lines, o + i, along_rows, causal)
        if i == n - 1:
            break
        i += 1
        causal = _load(src, lines, o + i, along_rows) + z * causal
    anti = ti.static(POLE / (POLE * POLE - 1.0)) * (causal + z * _load(dst, lines, o + n - 2, along_rows))
    while True:  # step i stores c⁻[i] and loads c⁺[i − 1], from i = n − 1 (where the causal loop ended) down
        _store(dst, lines, o + i, along_rows, gain * anti)
        if i == 0:
            break
        i -= 1
        anti = z * (anti - _load(dst, lines, o + i, along_rows))


@ti.kernel
def bspline_coefficients(image: ti.types.ndarray(dtype=ti.f32, ndim=2), out: ti.types.ndarray(dtype=ti.f32, ndim=2),
                         window: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """`out` ← the cubic B-spline coefficients of `image` over `window = (r0, r1, c0, c1)` (buffers as
    `check_buffers` accepts; module docstring)."""
    r0, r1, c0, c1 = window[0], window[1], window[2], window[3]
    for b in range((r1 - r0 + LANES - 1) // LANES):  # along the rows: c⁻ into out
        _lines(image, out, r0 + b * LANES, c1 - c0, r1 - 1, True, 1.0, c0)
    for b in range((c1 - c0 + LANES - 1) // LANES):  # then along the columns, in place, with the gain 6² of both axes
        _lines(out, out, c0 + b * LANES, r1 - r0, c1 - 1, False, 36.0, r0)


def check_buffers(image: NDArray[np.float32], out: NDArray[np.float32], window: NDArray[np.int32]) -> None:
    """Raise ValueError unless both images are C-contiguous float32 of the same shape and `window` is an int32
    `(r0, r1, c0, c1)` inside them with at least `HORIZON` rows and columns (the causal start sums `HORIZON` samples
    of each line)."""
    for name, arr in (("image", image), ("out", out)):
        if arr.dtype != np.float32 or arr.ndim != 2 or not arr.flags.c_contiguous:
            raise ValueError(f"{name} must be a C-contiguous 2-D float32 array, got {arr.dtype} {arr.shape}")
    if image.shape != out.shape:
        raise ValueError(f"image {image.shape} and out {out.shape} must have the same shape")
    if window.dtype != np.int32 or window.shape != (4,):
        raise ValueError(f"window must be an int32 array (r0, r1, c0, c1), got {window.dtype} {window.shape}")
    r0, r1, c0, c1 = (int(v) for v in window)
    if not (r0 >= 0 and c0 >= 0 and r1 <= image.shape[0] and c1 <= image.shape[1]
            and min(r1 - r0, c1 - c0) >= HORIZON):
        raise ValueError(f"window (r0={r0}, r1={r1}, c0={c0}, c1={c1}) must lie inside the {image.shape[1]}×"
                         f"{image.shape[0]} image and span at least {HORIZON} × {HORIZON}")


def window_for(shape: tuple[int, int], x_lo: float, y_lo: float, x_hi: float, y_hi: float) -> NDArray[np.int32]:
    """The window `(r0, r1, c0, c1)` whose coefficients are exact (module docstring) for every cubic sample at
    `x_lo ≤ x ≤ x_hi`, `y_lo ≤ y ≤ y_hi` (columns, rows; its taps reach 1 before and 2 after the point), clipped to
    the image of `shape` (rows, columns)."""
    h, w = shape
    reach = HORIZON + 2
    c0 = max(0, min(math.floor(x_lo) - reach, w - HORIZON))
    r0 = max(0, min(math.floor(y_lo) - reach, h - HORIZON))
    c1 = min(w, max(math.floor(x_hi) + reach + 1, c0 + HORIZON))
    r1 = min(h, max(math.floor(y_hi) + reach + 1, r0 + HORIZON))
    return np.array([r0, r1, c0, c1], dtype=np.int32)


def coefficients(image: NDArray[np.float32], out: NDArray[np.float32], window: NDArray[np.int32] | None = None) -> None:
    """Checked `bspline_coefficients(image, out, window)`; the whole image when `window` is None."""
    if window is None:
        window = np.array([0, image.shape[0], 0, image.shape[1]], dtype=np.int32)
    check_buffers(image, out, window)
    with compile_settings(advanced=True):  # as the registration compiles it (`spline_window`)
        bspline_coefficients(image, out, window)
