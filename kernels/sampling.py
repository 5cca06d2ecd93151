"""Taichi functions shared by the registration kernels: homography mapping, bilinear sampling, gain surface.

Conventions: images are `[row, col]` float32 arrays; pixel coordinates are 0-based pixel centres, `u` = column,
`v` = row. A point is *inside* an image of size H×W when `0 ≤ u ≤ W − 1` and `0 ≤ v ≤ H − 1` (all four bilinear
neighbours exist); samples outside are reported invalid and must be excluded by the caller (no border extension).

A kernel with a robot axis (`planar_step`) takes stacks instead: images `[k, row, col]`, parameter and work arrays
`[k, i]`, robot `k`'s image or row being what a kernel of one robot takes whole. The functions below read either
form (the array's dimension decides at compile time; `k` is ignored for a single image or a 1-D array), so one
kernel source serves one robot (a stack of one, or a plain array) and many.
"""


import taichi as ti


@ti.func
def entry(a: ti.template(), k: ti.i32, i: ti.i32) -> ti.f32:
    """`a[i]` of a 1-D array, `a[k, i]` of a 2-D stack of robots' arrays (module docstring)."""
    value = 0.0
    if ti.static(len(a.shape) == 2):  # noqa: SIM108 - Taichi compiles both branches of a conditional expression
        value = a[k, i]
    else:
        value = a[i]
    return value


@ti.func
def put_entry(a: ti.template(), k: ti.i32, i: ti.i32, value: ti.f32):
    """Store `value` at `entry(a, k, i)`."""
    if ti.static(len(a.shape) == 2):
        a[k, i] = value
    else:
        a[i] = value


@ti.func
def stack_size(a: ti.template()) -> ti.i32:
    """Robots in a stack of 2-D rows (`a.shape[0]`); 1 for one robot's 1-D array."""
    n = 1
    if ti.static(len(a.shape) == 2):
        n = a.shape[0]
    return n


@ti.func
def texel(img: ti.template(), k: ti.i32, row: ti.i32, col: ti.i32) -> ti.f32:
    """`img[row, col]` of one image, `img[k, row, col]` of a stack of robots' images (module docstring)."""
    value = 0.0
    if ti.static(len(img.shape) == 3):  # noqa: SIM108 - as in `entry`
        value = img[k, row, col]
    else:
        value = img[row, col]
    return value


@ti.func
def image_size(img: ti.template()):
    """`(rows, columns)` of one image, or of each image of a stack."""
    n = ti.static(len(img.shape))
    return img.shape[n - 2], img.shape[n - 1]


@ti.func
def load_vector(params: ti.template(), off: ti.template(), n: ti.template(), k=0):
    """`params[off:off + n]` (of robot `k`'s row of a stack: `entry`) as a local vector: read once before a pixel
    loop, the values stay in registers."""
    out = ti.Vector.zero(ti.f32, n)
    for i in ti.static(range(n)):
        out[i] = entry(params, k, off + i)
    return out


@ti.func
def homography_apply(G: ti.template(), u: ti.f32, v: ti.f32):
    """Homogeneous image `[x, y, z] = G · [u, v, 1]` of a pixel, `G` a row-major 9-vector (`load_vector`)."""
    x = G[0] * u + G[1] * v + G[2]
    y = G[3] * u + G[4] * v + G[5]
    z = G[6] * u + G[7] * v + G[8]
    return x, y, z


@ti.func
def bilinear(img: ti.template(), x: ti.f32, y: ti.f32, k=0):
    """Bilinear sample of `img` (robot `k`'s image of a stack: `texel`) at column `x`, row `y`; returns `(value, ok)`
    with `ok = 0` outside (value 0).

    Branch-free: the four taps are read at the clamped point (always in bounds, NaN included) and the result is
    selected, so that a pixel loop calling it can be vectorised."""
    h, w = image_size(img)
    inside = (x >= 0.0) & (y >= 0.0) & (x <= w - 1.0) & (y <= h - 1.0)  # `and` would be a branch
    xc = ti.min(ti.max(x, 0.0), w - 1.0)
    yc = ti.min(ti.max(y, 0.0), h - 1.0)
    x0 = ti.max(ti.min(ti.cast(xc, ti.i32), w - 2), 0)  # xc ≥ 0: truncation is the floor
    y0 = ti.max(ti.min(ti.cast(yc, ti.i32), h - 2), 0)
    ax = xc - x0
    ay = yc - y0
    top = (1.0 - ax) * texel(img, k, y0, x0) + ax * texel(img, k, y0, x0 + 1)
    bottom = (1.0 - ax) * texel(img, k, y0 + 1, x0) + ax * texel(img, k, y0 + 1, x0 + 1)
    return ti.select(inside, (1.0 - ay) * top + ay * bottom, 0.0), ti.select(inside, 1, 0)


@ti.func
def projected_sample(img: ti.template(), x: ti.f32, y: ti.f32, z: ti.f32, k=0):
    """Bilinear sample (of robot `k`'s image of a stack) at the dehomogenised point `(x / z, y / z)`; invalid when
    `z ≤ 1e-8` or outside the image. Branch-free, as `bilinear`."""
    ok_z = z > 1e-8
    iz = 1.0 / ti.select(ok_z, z, 1.0)
    val, ok = bilinear(img, x * iz, y * iz, k)
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
