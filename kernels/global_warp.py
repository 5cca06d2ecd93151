"""Bilinear sampling of an image through a stack of homographies (the global initialiser renders its hypotheses and
its rotated/scaled search templates with it, all of them in one launch), or at a list of points (the warp of a
model that is not a homography, e.g. eq. (2)).

`out[k, r, c] = src(H_k · [c + c0, r + r0, 1])` for the 3×3 matrices `H_k` (row-major in `h9[k, :]`; each maps output
pixel coordinates shifted by the offset `(c0, r0)` to source pixel coordinates; 0-based pixel centres, u = column,
v = row). `valid[k, r, c]` is 1 where the mapped point lies inside the source (all four bilinear neighbours exist),
else 0 and `out` is 0 there.
"""

import taichi as ti

from kernels.sampling import bilinear


@ti.kernel
def warp_homographies(
    src: ti.types.ndarray(dtype=ti.f32, ndim=2),
    out: ti.types.ndarray(dtype=ti.f32, ndim=3),
    valid: ti.types.ndarray(dtype=ti.f32, ndim=3),
    h9: ti.types.ndarray(dtype=ti.f32, ndim=2),
    c0: ti.f32,
    r0: ti.f32,
):
    """Sample `src` bilinearly at `H_k · [c + c0, r + r0, 1]` for every (k, r, c); see the module docstring."""
    hs, ws = src.shape[0], src.shape[1]
    for k, r, c in ti.ndrange(out.shape[0], out.shape[1], out.shape[2]):
        u = c + c0
        v = r + r0
        zw = h9[k, 6] * u + h9[k, 7] * v + h9[k, 8]
        val = 0.0
        ok = 0.0
        if ti.abs(zw) > 1e-12:
            x = (h9[k, 0] * u + h9[k, 1] * v + h9[k, 2]) / zw
            y = (h9[k, 3] * u + h9[k, 4] * v + h9[k, 5]) / zw
            if 0.0 <= x <= ws - 1.0 and 0.0 <= y <= hs - 1.0:
                xi = ti.min(ti.cast(ti.floor(x), ti.i32), ws - 2)
                yi = ti.min(ti.cast(ti.floor(y), ti.i32), hs - 2)
                ax = x - xi
                ay = y - yi
                top = (1.0 - ax) * src[yi, xi] + ax * src[yi, xi + 1]
                bot = (1.0 - ax) * src[yi + 1, xi] + ax * src[yi + 1, xi + 1]
                val = (1.0 - ay) * top + ay * bot
                ok = 1.0
        out[k, r, c] = val
        valid[k, r, c] = ok


@ti.kernel
def sample_points(
    src: ti.types.ndarray(dtype=ti.f32, ndim=2),
    points: ti.types.ndarray(dtype=ti.f32, ndim=2),
    out: ti.types.ndarray(dtype=ti.f32, ndim=1),
    valid: ti.types.ndarray(dtype=ti.f32, ndim=1),
):
    """`out[i] = src(points[i])` (bilinear; `points[i] = (u, v)`, source pixels) and `valid[i]` = 1 where all four
    neighbours exist (else 0, `out` 0), as `warp_homographies`."""
    for i in range(points.shape[0]):
        val, ok = bilinear(src, points[i, 0], points[i, 1])
        out[i] = val
        valid[i] = ti.cast(ok, ti.f32)
