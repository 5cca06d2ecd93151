"""Taichi ray casting of an analytic textured surface (plane or saddle) into a grey image with its depth.

One kernel launch renders a frame: per pixel, the ray `K⁻¹ [u, v, 1]` (camera frame, 0-based pixel centres) is
taken to the surface's local frame, intersected analytically (plane `z = 0` or saddle `z = (x² − y²)/a`, first hit in
front of the camera), the texture is sampled bilinearly (mirrored repeat) at the hit's local `(x, y)`, then the
illumination `S · I + β` and seeded Gaussian noise are applied. Float32 throughout. Geometry conventions and the
float64 reference intersection: `sim/surfaces.py`. Parameters are packed in one float32 array (layout `P_*`).
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
P_SIZE = 31


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
def _first_positive(s1: ti.f32, s2: ti.f32) -> ti.f32:
    s = ti.math.inf
    if s1 > 0.0:
        s = s1
    if s2 > 0.0 and s2 < s:
        s = s2
    return s


@ti.kernel
def _render(
    p: ti.types.ndarray(dtype=ti.f32, ndim=1),
    texture: ti.types.ndarray(dtype=ti.f32, ndim=2),
    image: ti.types.ndarray(dtype=ti.f32, ndim=2),
    depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
    key: ti.u32,
):
    # Parameters read once into registers: inside the loop the compiler could not hoist loads that may alias
    # the output arrays.
    k00, k01, k02, k11, k12 = p[P_KINV], p[P_KINV + 1], p[P_KINV + 2], p[P_KINV + 3], p[P_KINV + 4]
    r00, r01, r02 = p[P_R + 0], p[P_R + 1], p[P_R + 2]
    r10, r11, r12 = p[P_R + 3], p[P_R + 4], p[P_R + 5]
    r20, r21, r22 = p[P_R + 6], p[P_R + 7], p[P_R + 8]
    ox, oy, oz = p[P_O], p[P_O + 1], p[P_O + 2]
    saddle = p[P_KIND] > 0.5
    a = p[P_A]
    g0, g1, g2, g3, g4, g5 = p[P_GAIN], p[P_GAIN + 1], p[P_GAIN + 2], p[P_GAIN + 3], p[P_GAIN + 4], p[P_GAIN + 5]
    bias, sigma, background, quantize = p[P_BIAS], p[P_NOISE], p[P_BACKGROUND], p[P_QUANTIZE] > 0.5
    th, tw = texture.shape[0], texture.shape[1]
    su = tw / p[P_EXTENT]  # texels per metre
    sv = th / p[P_EXTENT + 1]
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
        if not saddle:
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
        value = background
        if s < ti.math.inf:
            u = _mirror((ox + s * dx) * su + 0.5 * tw - 0.5, tw)
            v = _mirror((oy + s * dy) * sv + 0.5 * th - 0.5, th)
            u0 = ti.min(ti.max(ti.cast(ti.floor(u), ti.i32), 0), tw - 1)
            v0 = ti.min(ti.max(ti.cast(ti.floor(v), ti.i32), 0), th - 1)
            u1 = ti.min(u0 + 1, tw - 1)
            v1 = ti.min(v0 + 1, th - 1)
            fu = ti.min(ti.max(u - u0, 0.0), 1.0)
            fv = ti.min(ti.max(v - v0, 0.0), 1.0)
            top = texture[v0, u0] + fu * (texture[v0, u1] - texture[v0, u0])
            bottom = texture[v1, u0] + fu * (texture[v1, u1] - texture[v1, u0])
            gain = g0 + g1 * xn + g2 * yn + g3 * xn * xn + g4 * xn * yn + g5 * yn * yn
            value = gain * (top + fv * (bottom - top)) + bias
        if sigma > 0.0:
            h1 = _hash(key ^ _hash(ti.cast(i, ti.u32) * ti.u32(2)))
            h2 = _hash(h1 ^ ti.u32(0x9E3779B9))
            u1n = (ti.cast(h1 >> 8, ti.f32) + 0.5) / 16777216.0
            u2n = ti.cast(h2 >> 8, ti.f32) / 16777216.0
            value += sigma * ti.sqrt(-2.0 * ti.log(u1n)) * ti.cos(6.283185307179586 * u2n)
        if quantize:
            value = ti.min(ti.max(ti.round(value), 0.0), 255.0)
        image[row, col] = value
        depth[row, col] = s


def render(
    params: NDArray[np.float32],
    texture: NDArray[np.float32],
    image: NDArray[np.float32],
    depth: NDArray[np.float32],
    key: int,
) -> None:
    """Render into the preallocated C-contiguous float32 arrays `image` and `depth` (same (H, W) shape; depth is
    camera-frame Z in metres, `inf` where the ray misses). `key` (uint32) seeds the noise of this frame."""
    if params.shape != (P_SIZE,) or params.dtype != np.float32:
        raise ValueError(f"params must be float32 of shape ({P_SIZE},), got {params.dtype} {params.shape}")
    for name, arr in (("texture", texture), ("image", image), ("depth", depth)):
        if arr.dtype != np.float32 or arr.ndim != 2 or not arr.flags.c_contiguous:
            raise ValueError(f"{name} must be a C-contiguous 2-D float32 array, got {arr.dtype} {arr.shape}")
    if image.shape != depth.shape:
        raise ValueError(f"image {image.shape} and depth {depth.shape} must have the same shape")
    _render(params, texture, image, depth, np.uint32(key & 0xFFFFFFFF))
