"""`registration.spline_window`: B-spline coefficients prefiltered around the sampled box, exact in its domain,
kept while later boxes stay inside it, renewed when one leaves it or a new image is loaded."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ddvs_service.registration.spline_window import UNRESTRICTED, SplineWindow
from kernels.backend import init
from kernels.bspline import coefficients


def whole(image: np.ndarray) -> np.ndarray:
    out = np.empty_like(image)
    coefficients(image, out)
    return out


def exact_part(domain: tuple[float, float, float, float], shape: tuple[int, int]) -> tuple[slice, slice]:
    """Rows and columns a cubic sample inside `domain` reads (1 before, 2 after the point), clipped."""
    x_lo, y_lo, x_hi, y_hi = domain
    rows = slice(max(0, math.floor(y_lo) - 1), min(shape[0], math.floor(y_hi) + 3))
    cols = slice(max(0, math.floor(x_lo) - 1), min(shape[1], math.floor(x_hi) + 3))
    return rows, cols


def test_window_is_exact_kept_and_renewed() -> None:
    init()
    rng = np.random.default_rng(2)
    image = rng.uniform(0.0, 255.0, (120, 160)).astype(np.float32)
    window = SplineWindow(image.shape, margin_px=6.0)
    box = (40.0, 30.0, 80.0, 60.0)
    buffer = window.covering(image, box)
    assert window.domain == (34.0, 24.0, 86.0, 66.0)
    rows, cols = exact_part(window.domain, image.shape)
    np.testing.assert_allclose(buffer[rows, cols], whole(image)[rows, cols], rtol=1e-5, atol=2e-3)
    assert np.count_nonzero(buffer) < 0.7 * buffer.size  # only a window was filtered

    domain = window.domain
    window.covering(image, (42.0, 31.0, 84.0, 62.0))  # inside: the same coefficients
    assert window.domain == domain

    window.covering(image, (90.0, 70.0, 150.0, 110.0))  # outside: a new window, exact there
    rows, cols = exact_part(window.domain, image.shape)
    np.testing.assert_allclose(buffer[rows, cols], whole(image)[rows, cols], rtol=1e-5, atol=2e-3)

    image[:] = rng.uniform(0.0, 255.0, image.shape)  # a new frame in the same buffer
    window.invalidate()
    assert window.domain is None
    window.covering(image, box)
    rows, cols = exact_part(window.domain, image.shape)
    np.testing.assert_allclose(buffer[rows, cols], whole(image)[rows, cols], rtol=1e-5, atol=2e-3)


def test_non_finite_box_filters_the_whole_image() -> None:
    init()
    image = np.random.default_rng(3).uniform(0.0, 255.0, (40, 50)).astype(np.float32)
    window = SplineWindow(image.shape, margin_px=4.0)
    buffer = window.covering(image, (math.nan, 0.0, 10.0, 10.0))
    assert window.domain == UNRESTRICTED
    np.testing.assert_allclose(buffer, whole(image), rtol=1e-5, atol=2e-3)


def test_negative_margin_is_refused() -> None:
    with pytest.raises(ValueError, match="margin_px"):
        SplineWindow((40, 50), margin_px=-1.0)
