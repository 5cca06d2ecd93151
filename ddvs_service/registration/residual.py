"""The residual image of a registration over its ROI: what the engine minimises, pixel by pixel.

`r(p*) = S(p*) · I(w(p*)) + β − I*(p*)` for every reference pixel `p*` of the ROI (eq. (4)–(5)): the current
image `I` sampled bilinearly at `w(p*)` (reference → current pixels, 0-based pixel centres) — `G p*` for the planar
model, eq. (2) `G p* + ρ*(p*) e` for the general one — the bilinear gain surface
`S` of the `gain_grid` nodes spread evenly over the ROI (as `kernels.planar_step.gain_at` evaluates it), the bias
`β`. With the camera response `gamma` and the relative defocus `defocus_px`, both images are compared as the engine
compares them (`images.irradiance`: the current image linearised, the reference linearised and blurred). Grey
levels; NaN where `G p*` falls outside the current image. A converged registration leaves noise, occlusions and
what the model cannot explain (parallax, specularities); a failed one shows the misalignment.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ddvs_service.registration.images import irradiance

Roi = tuple[int, int, int, int]
Parallax = tuple[NDArray[np.float64], NDArray[np.float64]]  # (ρ* over the ROI, h×w; e, 3): eq. (2)


def gain_surface(gains: NDArray[np.float64], width: int, height: int) -> NDArray[np.float32]:
    """`S(p*)` over a `width`×`height` ROI from its R×C node values (bilinear tents, nodes at the ROI's corners and
    evenly between; one node: a constant)."""
    rows, cols = gains.shape

    def weights(n_nodes: int, n_pixels: int) -> NDArray[np.float64]:
        t = np.linspace(0.0, n_nodes - 1.0, n_pixels) if n_nodes > 1 else np.zeros(n_pixels)
        return np.maximum(0.0, 1.0 - np.abs(t[:, None] - np.arange(n_nodes)[None, :]))

    return (weights(rows, height) @ gains @ weights(cols, width).T).astype(np.float32)


def residual_image(reference: NDArray, current: NDArray, roi: Roi, G: NDArray[np.float64],
                   gains: NDArray[np.float64], beta: float, gamma: float = 1.0,
                   defocus_px: float = 0.0, parallax: Parallax | None = None) -> NDArray[np.float32]:
    """`r(p*)` (module docstring) as an h×w float32 image of the ROI `(x, y, w, h)`; `reference` and `current` are
    grey images (any real dtype) of the same size. `parallax`: the general model's `(ρ*, e)`, ρ* as an h×w image
    over the ROI (gauge units) and `e` (3, same scale as `G`); None: planar."""
    x, y, w, h = roi
    ref = irradiance(np.ascontiguousarray(reference, dtype=np.float32), gamma, defocus_px)
    cur = irradiance(np.ascontiguousarray(current, dtype=np.float32), gamma)
    warped = sample_bilinear(cur, warp_points(np.asarray(G, dtype=np.float64), roi, parallax))
    S = gain_surface(np.atleast_2d(np.asarray(gains, dtype=np.float64)), w, h)
    return S * warped + np.float32(beta) - ref[y:y + h, x:x + w]


def warp_points(G: NDArray[np.float64], roi: Roi, parallax: Parallax | None = None) -> NDArray[np.float64]:
    """`G p*` (with `parallax` `(ρ*, e)`: `G p* + ρ*(p*) e`, eq. (2)) for every pixel `p*` of the ROI: an h×w×2
    array of (u, v) current-image coordinates."""
    x, y, w, h = roi
    v, u = np.mgrid[y:y + h, x:x + w].astype(np.float64)
    q = np.einsum("ij,jhw->ihw", G, np.stack([u, v, np.ones_like(u)]))
    if parallax is not None:
        rho, e = parallax
        q = q + np.asarray(e, dtype=np.float64)[:, None, None] * np.asarray(rho, dtype=np.float64)[None]
    return np.stack([q[0] / q[2], q[1] / q[2]], axis=-1)


def sample_bilinear(image: NDArray[np.float32], points: NDArray[np.float64]) -> NDArray[np.float32]:
    """`image` at `points` (…×2, (u, v), 0-based pixel centres), bilinear, exact (no fixed-point coordinates);
    NaN outside `[0, W − 1] × [0, H − 1]`."""
    u, v = points[..., 0], points[..., 1]
    inside = (u >= 0) & (v >= 0) & (u <= image.shape[1] - 1) & (v <= image.shape[0] - 1)
    u0 = np.clip(np.floor(u), 0, image.shape[1] - 2).astype(np.intp)
    v0 = np.clip(np.floor(v), 0, image.shape[0] - 2).astype(np.intp)
    a, b = np.where(inside, u - u0, 0.0), np.where(inside, v - v0, 0.0)
    top = image[v0, u0] * (1 - a) + image[v0, u0 + 1] * a
    bottom = image[v0 + 1, u0] * (1 - a) + image[v0 + 1, u0 + 1] * a
    return np.where(inside, top * (1 - b) + bottom * b, np.nan).astype(np.float32)
