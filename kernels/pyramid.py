"""Image pyramid: one octave down with a separable [1, 3, 3, 1] / 8 filter and 2× decimation.

Pixel-centre convention: level-(l+1) pixel `(c, r)` is centred on level-l point `(2c + 0.5, 2r + 0.5)`, i.e.
`p_{l+1} = (p_l + 0.5) / 2 − 0.5`; the 4×4 filter taps `2c − 1 … 2c + 2` are symmetric about that point.
Taps beyond the border are clamped. Masked pixels (`planar_step.MASKED`, −1e7) propagate: any masked tap
leaves the output below −1e5.
"""


import taichi as ti

TAPS = (1.0 / 8.0, 3.0 / 8.0, 3.0 / 8.0, 1.0 / 8.0)  # compile-time constants (`ti.static`), not a vector read per pixel


@ti.kernel
def downsample2(src: ti.types.ndarray(dtype=ti.f32, ndim=2), dst: ti.types.ndarray(dtype=ti.f32, ndim=2)):
    """`dst` (shape `(H // 2, W // 2)` of `src`) = filtered and decimated `src` (module docstring). Rows in parallel,
    each row's pixels in a serial inner loop (a flat loop over all pixels divides its index by the width at every
    pixel)."""
    h = src.shape[0]
    w = src.shape[1]
    for r in range(dst.shape[0]):
        for c in range(dst.shape[1]):
            acc = 0.0
            for i in ti.static(range(4)):
                row = ti.min(ti.max(2 * r - 1 + i, 0), h - 1)
                line = 0.0
                for j in ti.static(range(4)):
                    col = ti.min(ti.max(2 * c - 1 + j, 0), w - 1)
                    line += ti.static(TAPS[j]) * src[row, col]
                acc += ti.static(TAPS[i]) * line
            dst[r, c] = acc
