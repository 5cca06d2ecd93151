"""Distances between homographies over a region of interest: how far two warps send the same pixels.

Used to compare candidate starts of the global initialiser and to measure registration accuracy. Pixel
coordinates are 0-based pixel centres (u right, v down); an ROI is `(x, y, w, h)` in pixels.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def roi_grid(roi: tuple[int, int, int, int]) -> F64:
    """Pixel centres of the ROI `(x, y, w, h)` as a (w·h, 2) array of (u, v)."""
    x, y, w, h = roi
    u, v = np.meshgrid(np.arange(x, x + w, dtype=np.float64), np.arange(y, y + h, dtype=np.float64))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def apply_homography(H: F64, points: F64) -> F64:
    """Map (N, 2) pixel points through H (dehomogenised)."""
    q = np.c_[points, np.ones(len(points))] @ H.T
    return q[:, :2] / q[:, 2:3]


def roi_samples(roi: tuple[int, int, int, int], n: int = 16) -> F64:
    """An n × n grid of (u, v) points spread evenly over the ROI from corner pixel centre to corner pixel centre, as
    a (n², 2) array: RMS distances over it approximate those over every ROI pixel (`roi_grid`) at a fraction of
    the cost, since a homography moves neighbouring pixels smoothly."""
    x, y, w, h = roi
    u, v = np.meshgrid(np.linspace(x, x + w - 1, n), np.linspace(y, y + h - 1, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def rms_distance(H_a: F64, H_b: F64, points: F64) -> float:
    """RMS distance (pixels) between where two homographies send the (N, 2) `points`."""
    return float(np.sqrt(np.mean(np.sum((apply_homography(H_a, points) - apply_homography(H_b, points)) ** 2,
                                        axis=1))))


def warp_rms(H_est: F64, H_true: F64, roi: tuple[int, int, int, int]) -> float:
    """RMS distance (pixels) between where two homographies send the ROI pixels."""
    return rms_distance(H_est, H_true, roi_grid(roi))
