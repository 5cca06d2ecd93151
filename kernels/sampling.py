"""Taichi functions shared by the registration kernels: homography mapping, bilinear sampling, gain surface.

Conventions: images are `[row, col]` float32 arrays; pixel coordinates are 0-based pixel centres, `u` = column,
`v` = row. A point is *inside* an image of size H×W when `0 ≤ u ≤ W − 1` and `0 ≤ v ≤ H − 1` (all four bilinear
neighbours exist); samples outside are reported invalid and must be excluded by the caller (no border extension).
"""


import taichi as ti


@ti.func
def load_vector(params: ti.template(), off: ti.template(), n: ti.template()):
    """`params[off:off + n]` as a local vector: read once before a pixel loop, the values stay in registers."""
    out = ti.Vector.zero(ti.f32, n)
    for k in ti.static(range(n)):
        out[k] = params[off + k]
    return out


@ti.func
def homography_apply(G: ti.template(), u: ti.f32, v: ti.f32):
    """Homogeneous image `[x, y, z] = G · [u, v, 1]` of a pixel, `G` a row-major 9-vector (`load_vector`)."""
    x = G[0] * u + G[1] * v + G[2]
    y = G[3] * u + G[4] * v + G[5]
    z = G[6] * u + G[7] * v + G[8]
    return x, y, z


@ti.func
def bilinear(img: ti.template(), x: ti.f32, y: ti.f32):
    """Bilinear sample of `img` at column `x`, row `y`; returns `(value, ok)` with `ok = 0` outside (value 0).

    Branch-free: the four taps are read at the clamped point (always in bounds, NaN included) and the result is
    selected, so that a pixel loop calling it can be vectorised."""
    h = img.shape[0]
    w = img.shape[1]
    inside = (x >= 0.0) & (y >= 0.0) & (x <= w - 1.0) & (y <= h - 1.0)  # `and` would be a branch
    xc = ti.min(ti.max(x, 0.0), w - 1.0)
    yc = ti.min(ti.max(y, 0.0), h - 1.0)
    x0 = ti.max(ti.min(ti.cast(xc, ti.i32), w - 2), 0)  # xc ≥ 0: truncation is the floor
    y0 = ti.max(ti.min(ti.cast(yc, ti.i32), h - 2), 0)
    ax = xc - x0
    ay = yc - y0
    top = (1.0 - ax) * img[y0, x0] + ax * img[y0, x0 + 1]
    bottom = (1.0 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]
    return ti.select(inside, (1.0 - ay) * top + ay * bottom, 0.0), ti.select(inside, 1, 0)


@ti.func
def projected_sample(img: ti.template(), x: ti.f32, y: ti.f32, z: ti.f32):
    """Bilinear sample at the dehomogenised point `(x / z, y / z)`; invalid when `z ≤ 1e-8` or outside the image.
    Branch-free, as `bilinear`."""
    ok_z = z > 1e-8
    iz = 1.0 / ti.select(ok_z, z, 1.0)
    val, ok = bilinear(img, x * iz, y * iz)
    return ti.select(ok_z, val, 0.0), ti.select(ok_z, ok, 0)


@ti.func
def tent(t: ti.f32, node: ti.f32) -> ti.f32:
    """Linear interpolation weight of grid node `node` at grid coordinate `t` (the 1-D bilinear basis)."""
    return ti.max(0.0, 1.0 - ti.abs(t - node))


@ti.func
def grid_coordinate(x: ti.f32, lo: ti.f32, hi: ti.f32, n: ti.template()) -> ti.f32:
    """Grid coordinate in `[0, n − 1]` of `x` for `n` nodes spread evenly from `lo` to `hi` (0 when `n == 1`)."""
    t = 0.0
    if ti.static(n > 1):
        t = ti.min(ti.max((x - lo) / ti.max(hi - lo, 1e-6), 0.0), 1.0) * (n - 1)
    return t
