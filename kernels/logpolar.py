"""Log-polar resampling of a centred (fft-shifted) magnitude spectrum, for Fourier–Mellin registration.

Input: a real 2-D array `spec[row, col]` of shape (h, w) whose zero frequency sits at `(row, col) = (h // 2, w // 2)`
(the layout of `numpy.fft.fftshift`). Output `out[i, j]` samples the spectrum (bilinear) at the frequency of radius
`ρ_i = exp(log_rho0 + i · dlog_rho)` cycles per pixel and angle `θ_j = j · dtheta` radians, measured from the +u axis
(columns, right) towards +v (rows, down): frequency `(f_u, f_v) = ρ (cos θ, sin θ)` lies at column `w//2 + f_u · w`,
row `h//2 + f_v · h`. Samples outside the array read 0. Frequencies in cycles/pixel make spectra of different sizes
directly comparable.
"""

import taichi as ti
import taichi.math as tm


@ti.kernel
def logpolar_resample(
    spec: ti.types.ndarray(dtype=ti.f32, ndim=2),
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),
    log_rho0: ti.f32,
    dlog_rho: ti.f32,
    dtheta: ti.f32,
):
    """Fill `out[i, j]` with `spec` sampled at radius `exp(log_rho0 + i·dlog_rho)` (cycles/px), angle `j·dtheta`."""
    h, w = spec.shape[0], spec.shape[1]
    for i, j in ti.ndrange(out.shape[0], out.shape[1]):
        rho = tm.exp(log_rho0 + i * dlog_rho)
        theta = j * dtheta
        x = (w // 2) + rho * tm.cos(theta) * w
        y = (h // 2) + rho * tm.sin(theta) * h
        x0 = ti.floor(x)
        y0 = ti.floor(y)
        ax = x - x0
        ay = y - y0
        c0 = ti.cast(x0, ti.i32)
        r0 = ti.cast(y0, ti.i32)
        acc = 0.0
        for dr, dc in ti.static(ti.ndrange(2, 2)):
            r = r0 + dr
            c = c0 + dc
            wgt = (ax if dc == 1 else 1.0 - ax) * (ay if dr == 1 else 1.0 - ay)
            if 0 <= r < h and 0 <= c < w:
                acc += wgt * spec[r, c]
        out[i, j] = acc
