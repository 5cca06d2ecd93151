"""Cubic B-spline prefilter (`kernels.bspline`): the interpolating spline passes through every sample, borders and
line counts that are not a multiple of the kernel's lanes included; bad buffers are refused."""

from __future__ import annotations

import numpy as np
import pytest

from kernels.backend import init
from kernels.bspline import HORIZON, LANES, coefficients, window_for


def spline_at_samples(c: np.ndarray) -> np.ndarray:
    """`Σ_k c[k] β³(i − k)` at every sample `i` of both axes: `(c[i−1] + 4 c[i] + c[i+1]) / 6`, mirror boundary."""
    for axis in (0, 1):
        p = np.pad(c, [(1, 1) if a == axis else (0, 0) for a in (0, 1)], mode="reflect")
        n = c.shape[axis]
        c = (np.take(p, range(0, n), axis) + 4.0 * np.take(p, range(1, n + 1), axis)
             + np.take(p, range(2, n + 2), axis)) / 6.0
    return c


@pytest.mark.parametrize("shape", [(37, 29), (2 * LANES, 3 * LANES + 1), (HORIZON, HORIZON)])
def test_coefficients_interpolate_every_sample(shape: tuple[int, int]) -> None:
    init()
    image = np.random.default_rng(4).uniform(0.0, 255.0, shape).astype(np.float32)
    out = np.empty_like(image)
    coefficients(image, out)
    np.testing.assert_allclose(spline_at_samples(out.astype(np.float64)), image, atol=2e-3)
    assert np.std(out) > 1.5 * np.std(image)  # the inverse filter sharpens: c is not the image


@pytest.mark.parametrize("domain", [(20.0, 15.0, 40.5, 35.2), (1.0, 1.0, 10.0, 12.0), (50.0, 40.0, 67.9, 57.9)])
def test_window_gives_the_whole_image_coefficients_where_it_is_sampled(domain) -> None:
    """A window from `window_for` (inside, at a corner, at the far corner) filters only itself and, wherever a cubic
    sample in the domain reads, matches the whole image's coefficients."""
    init()
    image = np.random.default_rng(5).uniform(0.0, 255.0, (60, 70)).astype(np.float32)
    full = np.empty_like(image)
    coefficients(image, full)
    out = np.full_like(image, -999.0)
    window = window_for(image.shape, *domain)
    coefficients(image, out, window)
    r0, r1, c0, c1 = window
    outside = np.ones(image.shape, dtype=bool)
    outside[r0:r1, c0:c1] = False
    assert np.all(out[outside] == -999.0)
    x_lo, y_lo, x_hi, y_hi = domain
    rows = slice(max(0, int(y_lo) - 1), min(60, int(y_hi) + 3))
    cols = slice(max(0, int(x_lo) - 1), min(70, int(x_hi) + 3))
    np.testing.assert_allclose(out[rows, cols], full[rows, cols], rtol=1e-5, atol=2e-3)


def test_coefficients_refuse_bad_buffers() -> None:
    image = np.zeros((8, 8), dtype=np.float32)
    with pytest.raises(ValueError, match="same shape"):
        coefficients(image, np.zeros((8, 9), dtype=np.float32))
    with pytest.raises(ValueError, match="at least"):
        coefficients(image, np.zeros((8, 8), dtype=np.float32))
    image = np.zeros((HORIZON, HORIZON), dtype=np.float32)
    with pytest.raises(ValueError, match="float32"):
        coefficients(image, np.zeros((HORIZON, HORIZON)))
    with pytest.raises(ValueError, match="inside"):
        coefficients(image, np.zeros_like(image), np.array([0, HORIZON + 1, 0, HORIZON], dtype=np.int32))
    with pytest.raises(ValueError, match="int32"):
        coefficients(image, np.zeros_like(image), np.array([0, HORIZON, 0, HORIZON]))
