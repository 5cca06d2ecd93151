"""Bilinear sampling of an image through a homography (used by the global initialiser to render hypotheses).

`out[r, c] = src(H · [c + c0, r + r0, 1])` for the 3×3 matrix `H` (row-major in `h9`, maps output pixel coordinates
shifted by the offset `(c0, r0)` to source pixel coordinates; 0-based pixel centres, u = column, v = row).
`valid[r, c]` is 1 where the mapped point lies inside the source (all four bilinear neighbours exist), else 0 and
`out` is 0 there.
"""

import taichi as ti


@ti.kernel
def warp_homography(
    src: ti.types.ndarray(dtype=ti.f32, ndim=2),
    out: ti.types.ndarray(dtype=ti.f32, ndim=2),
    valid: ti.types.ndarray(dtype=ti.f32, ndim=2),
    h9: ti.types.ndarray(dtype=ti.f32, ndim=1),
    c0: ti.f32,
    r0: ti.f32,
):
    """Sample `src` bilinearly at `H · [c + c0, r + r0, 1]` for every output pixel (r, c); see the module docstring."""
    hs, ws = src.shape[0], src.shape[1]
    for r, c in ti.ndrange(out.shape[0], out.shape[1]):
        u = c + c0
        v = r + r0
        zw = h9[6] * u + h9[7] * v + h9[8]
        val = 0.0
        ok = 0.0
        if ti.abs(zw) > 1e-12:
            x = (h9[0] * u + h9[1] * v + h9[2]) / zw
            y = (h9[3] * u + h9[4] * v + h9[5]) / zw
            if 0.0 <= x <= ws - 1.0 and 0.0 <= y <= hs - 1.0:
                xi = ti.min(ti.cast(ti.floor(x), ti.i32), ws - 2)
                yi = ti.min(ti.cast(ti.floor(y), ti.i32), hs - 2)
                ax = x - xi
                ay = y - yi
                top = (1.0 - ax) * src[yi, xi] + ax * src[yi, xi + 1]
                bot = (1.0 - ax) * src[yi + 1, xi] + ax * src[yi + 1, xi + 1]
                val = (1.0 - ay) * top + ay * bot
                ok = 1.0
        out[r, c] = val
        valid[r, c] = ok
