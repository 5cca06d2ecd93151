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
"""

import math

import numpy as np
import taichi as ti
from numpy.typing import NDArray

POLE = math.sqrt(3.0) - 2.0
HORIZON = 12  # |z|^12 = 1.4e-7: the causal start's truncation, below float32 resolution
LANES = 8  # lines filtered together by one thread: independent recursions, so that their latencies overlap


@ti.func
def _at(a: ti.template(), line: ti.i32, i: ti.i32, along_rows: ti.template()) -> ti.f32:
    value = 0.0
    if ti.static(along_rows):  # noqa: SIM108 - a compile-time branch: Taichi takes `ti.static` in an if statement
        value = a[line, i]
    else:
        value = a[i, line]
    return value


@ti.func
def _set(a: ti.template(), line: ti.i32, i: ti.i32, along_rows: ti.template(), value: ti.f32):
    if ti.static(along_rows):
        a[line, i] = value
    else:
        a[i, line] = value


@ti.func
def _lines(src: ti.template(), dst: ti.template(), first: ti.i32, n: ti.i32, last_line: ti.i32,
           along_rows: ti.template(), gain: ti.template()):
    """Filter the `LANES` lines `first …` (rows when `along_rows`, else columns) of length `n` from `src` into `dst`
    (which may be `src`): `dst = gain · c⁻` (module docstring). Lanes past `last_line` repeat it: every step loads
    all lanes before it stores any, so a repeated line computes and stores the same values as its owner."""
    z = ti.static(POLE)
    lines = ti.Vector([ti.min(first + j, last_line) for j in ti.static(range(LANES))])
    causal = ti.Vector.zero(ti.f32, LANES)
    zk = 1.0
    for k in range(HORIZON):
        for j in ti.static(range(LANES)):
            causal[j] += zk * _at(src, lines[j], k, along_rows)
        zk *= z
    for i in range(1, n + 1):  # step i stores c⁺[i − 1] and loads s[i]
        for j in ti.static(range(LANES)):
            _set(dst, lines[j], i - 1, along_rows, causal[j])
        if i < n:
            loaded = ti.Vector([_at(src, lines[j], i, along_rows) for j in ti.static(range(LANES))])
            causal = loaded + z * causal
    anti = ti.static(POLE / (POLE * POLE - 1.0)) * (
        causal + z * ti.Vector([_at(dst, lines[j], n - 2, along_rows) for j in ti.static(range(LANES))]))
    for m in range(n):  # step m stores c⁻[n − 1 − m] and loads c⁺[n − 2 − m]
        i = n - 1 - m
        for j in ti.static(range(LANES)):
            _set(dst, lines[j], i, along_rows, gain * anti[j])
        if i > 0:
            loaded = ti.Vector([_at(dst, lines[j], i - 1, along_rows) for j in ti.static(range(LANES))])
            anti = z * (anti - loaded)


@ti.kernel
def bspline_coefficients(image: ti.types.ndarray(dtype=ti.f32, ndim=2), out: ti.types.ndarray(dtype=ti.f32, ndim=2)):
    """`out` ← the cubic B-spline coefficients of `image` (buffers as `check_buffers` accepts; module docstring)."""
    h, w = image.shape[0], image.shape[1]
    for b in range((h + LANES - 1) // LANES):  # along the rows: c⁻ into out
        _lines(image, out, b * LANES, w, h - 1, True, 1.0)
    for b in range((w + LANES - 1) // LANES):  # then along the columns, in place, with the gain 6² of both axes
        _lines(out, out, b * LANES, h, w - 1, False, 36.0)


def check_buffers(image: NDArray[np.float32], out: NDArray[np.float32]) -> None:
    """Raise ValueError unless both are C-contiguous float32 of the same shape with at least `HORIZON` rows and
    columns (the causal start sums `HORIZON` samples of each line)."""
    for name, arr in (("image", image), ("out", out)):
        if arr.dtype != np.float32 or arr.ndim != 2 or not arr.flags.c_contiguous:
            raise ValueError(f"{name} must be a C-contiguous 2-D float32 array, got {arr.dtype} {arr.shape}")
    if image.shape != out.shape or min(image.shape) < HORIZON:
        raise ValueError(f"image {image.shape} and out {out.shape} must have the same shape, at least "
                         f"{HORIZON} × {HORIZON}")


def coefficients(image: NDArray[np.float32], out: NDArray[np.float32]) -> None:
    """Checked `bspline_coefficients(image, out)`."""
    check_buffers(image, out)
    bspline_coefficients(image, out)
