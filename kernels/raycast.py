"""Taichi ray casting of an analytic textured surface (plane or saddle) into a grey image with its depth.

One kernel launch renders a frame: per pixel, the ray `K⁻¹ [u, v, 1]` (camera frame, 0-based pixel centres) is
taken to the surface's local frame, intersected analytically (plane `z = 0` or saddle `z = (x² − y²)/a`, first hit in
front of the camera), and the albedo at the hit's local `(x, y)` is read:
- tiled scene (`P_TILED` = 1): the texture, sampled bilinearly, repeated mirrored over the whole surface;
- finite target (`P_TILED` = 0): the texture inside the textured extent `[−w/2, w/2] × [−h/2, h/2]`, the `backdrop`
  array outside it (mirrored repeat, one backdrop tile per extent; a 1×1 array is a uniform grey), blended by the
  pixel's coverage of the extent: the pixel's footprint on the surface (the parallelogram of the ray differentials
  projected on the tangent plane) cut by each edge, x and y coverages multiplied (a box filter: anti-aliased edges;
  approximate only in the corner pixels).
Where the ray misses the surface the albedo is `P_BACKGROUND`. Then the illumination `S · albedo + β` and seeded
Gaussian noise are applied. Float32 throughout. Geometry conventions and the float64 reference intersection:
`sim/surfaces.py`. Parameters are packed in one float32 array (layout `P_*`).
"""

import numpy as np
import taichi as ti
from numpy.typing import NDArray

# Layout of the packed float32 parameter vector.
P_KINV = 0  # 5 entries: K⁻¹[0,0], K⁻¹[0,1], K⁻¹[0,2], K⁻¹[1,1], K⁻¹[1,2]
P_R = 5  # 9 entries: R_surface_cam, row-major
P_O = 14  # 3 entries: camera centre in the surface frame (m)
P_KIND = 17  # 0 plane, 1 saddle
P_A = 18  # saddle parameter a (m)
P_EXTENT = 19  # 2 entries: textured extent w, h (m)
P_GAIN = 21  # 6 entries: S = g0 + g1 x + g2 y + g3 x² + g4 x y + g5 y² over normalised image coordinates
P_BIAS = 27  # β (grey levels)
P_NOISE = 28  # standard deviation of the additive Gaussian noise (grey levels)
P_BACKGROUND = 29  # grey level where the ray misses
P_QUANTIZE = 30  # 1: round and clip to [0, 255] like an 8-bit sensor
P_TILED = 31  # 1: the texture repeats mirrored over the whole surface; 0: finite target on the backdrop
P_SIZE = 32


@ti.func
def _hash(x: ti.u32) -> ti.u32:
    """A 32-bit integer mixing function (lowbias32): counter-based, so the noise is deterministic."""
    x ^= x >> 16
    x *= ti.u32(0x7FEB352D)
    x ^= x >> 15
    x *= ti.u32(0x846CA68B)
    x ^= x >> 16
    return x


@ti.func
def _mirror(u: ti.f32, n: ti.i32) -> ti.f32:
    """Mirrored-repeat texel coordinate in [−0.5, n − 0.5] (pixel centres at integers)."""
    x = u + 0.5
    if x < 0.0 or x >= n:
        period = 2.0 * n
        x = x - ti.floor(x / period) * period
        if x >= n:
            x = period - x
    return x - 0.5


@ti.func
def _bilinear(texture: ti.template(), u: ti.f32, v: ti.f32) -> ti.f32:
    """Texture value at texel coordinates `(u, v)` (pixel centres at integers), bilinear, mirrored repeat."""
    th, tw = texture.shape[0], texture.shape[1]
    u = _mirror(u, tw)
    v = _mirror(v, th)
    u0 = ti.min(ti.max(ti.cast(ti.floor(u), ti.i32), 0), tw - 1)
    v0 = ti.min(ti.max(ti.cast(ti.floor(v), ti.i32), 0), th - 1)
    u1 = ti.min(u0 + 1, tw - 1)
    v1 = ti.min(v0 + 1, th - 1)
    fu = ti.min(ti.max(u - u0, 0.0), 1.0)
    fv = ti.min(ti.max(v - v0, 0.0), 1.0)
    top = texture[v0, u0] + fu * (texture[v0, u1] - texture[v0, u0])
    bottom = texture[v1, u0] + fu * (texture[v1, u1] - texture[v1, u0])
    return top + fv * (bottom - top)


@ti.func
def _tangent_step(s: ti.f32, d: ti.math.vec3, step: ti.math.vec3, n: ti.math.vec3) -> ti.math.vec3:
    """Displacement on the surface (local frame) of the hit `o + s d` when the ray direction changes by `step`:
    `s (step − d (n·step)/(n·d))`, the ray differential on the tangent plane of normal `n`."""
    nd = n.dot(d)
    result = ti.math.vec3(0.0, 0.0, 0.0)
    if nd != 0.0:
        result = s * (step - d * (n.dot(step) / nd))
    return result


@ti.func
def _coverage(half: ti.f32, x: ti.f32, a: ti.f32, b: ti.f32) -> ti.f32:
    """Fraction of a pixel centred at `x` inside `[−half, half]`, the pixel's footprint being the parallelogram whose
    sides span `a` and `b` (m) along x: the distribution of the sum of two uniform variables of widths `a` and `b`
    (a trapezoid), integrated up to the edge; exact for a straight edge and a locally affine projection."""
    p = ti.min(a, b)
    q = ti.max(ti.max(a, b), 1e-12)
    t = half - ti.abs(x) + 0.5 * (p + q)  # the edge's position in the footprint, from its outer end
    cover = 0.0
    if t >= p + q:
        cover = 1.0
    elif t > 0.0:
        if t < p:
            cover = t * t / (2.0 * p * q)
        elif t <= q:
            cover = (t - 0.5 * p) / q
        else:
            cover = 1.0 - (p + q - t) * (p + q - t) / (2.0 * p * q)
    return cover


@ti.func
def _first_positive(s1: ti.f32, s2: ti.f32) -> ti.f32:
    s = ti.math.inf
    if s1 > 0.0:
        s = s1
    if s2 > 0.0 and s2 < s:
        s = s2
    return s


@ti.func
def _switch(value: ti.f32) -> ti.i32:
    """A packed on/off parameter (0.0 or 1.0) as the integer 0 or 1."""
    return ti.select(value > 0.5, 1, 0)


@ti.kernel
def _render(
    p: ti.types.ndarray(dtype=ti.f32, ndim=1),
    texture: ti.types.ndarray(dtype=ti.f32, ndim=2),
    backdrop: ti.types.ndarray(dtype=ti.f32, ndim=2),
    image: ti.types.ndarray(dtype=ti.f32, ndim=2),
    depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
    key: ti.u32,
):
    # Parameters read once into registers: inside the loop the compiler could not hoist loads that may alias
    # the output arrays. The switches are integers: Taichi 1.7.4's SPIR-V code generation (Vulkan) gives every
    # boolean that the serial part hands to the pixel loop the same slot, so all of them read the last one's value.
    k00, k01, k02, k11, k12 = p[P_KINV], p[P_KINV + 1], p[P_KINV + 2], p[P_KINV + 3], p[P_KINV + 4]
    r00, r01, r02 = p[P_R + 0], p[P_R + 1], p[P_R + 2]
    r10, r11, r12 = p[P_R + 3], p[P_R + 4], p[P_R + 5]
    r20, r21, r22 = p[P_R + 6], p[P_R + 7], p[P_R + 8]
    ox, oy, oz = p[P_O], p[P_O + 1], p[P_O + 2]
    saddle = _switch(p[P_KIND])
    a = p[P_A]
    g0, g1, g2, g3, g4, g5 = p[P_GAIN], p[P_GAIN + 1], p[P_GAIN + 2], p[P_GAIN + 3], p[P_GAIN + 4], p[P_GAIN + 5]
    bias, sigma, background, quantize = p[P_BIAS], p[P_NOISE], p[P_BACKGROUND], _switch(p[P_QUANTIZE])
    tiled = _switch(p[P_TILED])
    half_w, half_h = 0.5 * p[P_EXTENT], 0.5 * p[P_EXTENT + 1]
    th, tw = texture.shape[0], texture.shape[1]
    su = tw / p[P_EXTENT]  # texels per metre
    sv = th / p[P_EXTENT + 1]
    bh, bw = backdrop.shape[0], backdrop.shape[1]
    bu = bw / p[P_EXTENT]
    bv = bh / p[P_EXTENT + 1]
    # Ray direction steps (local frame) of one pixel along u and along v.
    step_u = ti.math.vec3(r00 * k00, r10 * k00, r20 * k00)
    step_v = ti.math.vec3(r00 * k01 + r01 * k11, r10 * k01 + r11 * k11, r20 * k01 + r21 * k11)
    width = image.shape[1]
    for i in range(image.shape[0] * width):  # flat loop: split evenly over the CPU threads
        row = i // width
        col = i - row * width
        xn = k00 * col + k01 * row + k02
        yn = k11 * row + k12
        dx = r00 * xn + r01 * yn + r02
        dy = r10 * xn + r11 * yn + r12
        dz = r20 * xn + r21 * yn + r22
        s = ti.math.inf
        if saddle == 0:
            if dz != 0.0:
                s = _first_positive(-oz / dz, -1.0)
        else:
            qa = dx * dx - dy * dy
            qb = 2.0 * (ox * dx - oy * dy) - a * dz
            qc = ox * ox - oy * oy - a * oz
            if ti.abs(qa) > 1e-7 * ti.max(ti.abs(qb), 1.0):
                disc = qb * qb - 4.0 * qa * qc
                if disc >= 0.0:
                    q = -0.5 * (qb + ti.math.sign(qb) * ti.sqrt(disc))
                    if qb == 0.0:
                        q = -0.5 * ti.sqrt(disc)
                    if q != 0.0:
                        s = _first_positive(q / qa, qc / q)
            elif qb != 0.0:
                s = _first_positive(-qc / qb, -1.0)
        albedo = background
        if s < ti.math.inf:
            x = ox + s * dx
            y = oy + s * dy
            albedo = _bilinear(texture, x * su + 0.5 * tw - 0.5, y * sv + 0.5 * th - 0.5)
            if tiled == 0:
                n = ti.math.vec3(0.0, 0.0, 1.0)
                if saddle:
                    n = ti.math.vec3(2.0 * x / a, -2.0 * y / a, -1.0)
                d = ti.math.vec3(dx, dy, dz)
                du = _tangent_step(s, d, step_u, n)
                dv = _tangent_step(s, d, step_v, n)
                cover = _coverage(half_w, x, ti.abs(du[0]), ti.abs(dv[0])) * _coverage(
                    half_h, y, ti.abs(du[1]), ti.abs(dv[1])
                )
                back = _bilinear(backdrop, x * bu + 0.5 * bw - 0.5, y * bv + 0.5 * bh - 0.5)
                albedo = back + cover * (albedo - back)
        gain = g0 + g1 * xn + g2 * yn + g3 * xn * xn + g4 * xn * yn + g5 * yn * yn
        value = gain * albedo + bias
        if sigma > 0.0:
            h1 = _hash(key ^ _hash(ti.cast(i, ti.u32) * ti.u32(2)))
            h2 = _hash(h1 ^ ti.u32(0x9E3779B9))
            u1n = (ti.cast(h1 >> 8, ti.f32) + 0.5) / 16777216.0
            u2n = ti.cast(h2 >> 8, ti.f32) / 16777216.0
            value += sigma * ti.sqrt(-2.0 * ti.log(u1n)) * ti.cos(6.283185307179586 * u2n)
        if quantize == 1:
            value = ti.min(ti.max(ti.round(value), 0.0), 255.0)
        image[row, col] = value
        depth[row, col] = s


def render(
    params: NDArray[np.float32],
    texture: NDArray[np.float32],
    backdrop: NDArray[np.float32],
    image: NDArray[np.float32],
    depth: NDArray[np.float32],
    key: int,
) -> None:
    """Render into the preallocated C-contiguous float32 arrays `image` and `depth` (same (H, W) shape; depth is
    camera-frame Z in metres, `inf` where the ray misses). `backdrop` (2-D float32) is read only for a finite target
    (`P_TILED` = 0). `key` (uint32) seeds the noise of this frame."""
    if params.shape != (P_SIZE,) or params.dtype != np.float32:
        raise ValueError(f"params must be float32 of shape ({P_SIZE},), got {params.dtype} {params.shape}")
    for name, arr in (("texture", texture), ("backdrop", backdrop), ("image", image), ("depth", depth)):
        if arr.dtype != np.float32 or arr.ndim != 2 or not arr.flags.c_contiguous:
            raise ValueError(f"{name} must be a C-contiguous 2-D float32 array, got {arr.dtype} {arr.shape}")
    if image.shape != depth.shape:
        raise ValueError(f"image {image.shape} and depth {depth.shape} must have the same shape")
    _render(params, texture, backdrop, image, depth, np.uint32(key & 0xFFFFFFFF))
