"""Substrate roughness: a smooth random height field that can be evaluated anywhere.

A cubic B-spline with independent Gaussian coefficients on a grid whose spacing is the
correlation length: smooth (the tip follows it), stationary to within a few percent,
bounded, and the same field for full scans and single scan lines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from nanoasm.schema import Point


@dataclass(frozen=True, eq=False)
class Roughness:
    """Smooth random substrate height: a cubic B-spline with random coefficients.

    ``coeffs[k, l]`` sits at ``origin + (l, k) * spacing``; the field is
    ``scale * sum coeffs * B3``, so it is bounded by ``scale * max|coeffs|``.
    """

    coeffs: np.ndarray
    spacing: float
    origin: Point
    scale: float

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Heights at points ``(x, y)`` (arrays of one shape), in nm."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        coords = np.stack([((y - self.origin[1]) / self.spacing).ravel(),
                           ((x - self.origin[0]) / self.spacing).ravel()])
        z = ndimage.map_coordinates(self.coeffs, coords, order=3, prefilter=False, mode="nearest")
        return self.scale * z.reshape(x.shape)

    @property
    def bound(self) -> float:
        """Largest absolute height the field can take."""
        return float(self.scale * np.abs(self.coeffs).max())


def make_roughness(area: Point, rms: float, length: float, rng: np.random.Generator) -> Roughness:
    """Roughness of about ``rms`` nm with correlation length ``length`` nm over ``area``.

    The field covers ``area`` with a margin of 20 lengths so that drifted scans and
    windows near the border still see random (not clamped) roughness.
    """
    if not (math.isfinite(rms) and rms >= 0):
        raise ValueError(f"rms must be non-negative and finite, got {rms}")
    if not (math.isfinite(length) and length > 0):
        raise ValueError(f"length must be positive and finite, got {length}")
    margin = 20 * length
    nx = int(math.ceil((area[0] + 2 * margin) / length)) + 4
    ny = int(math.ceil((area[1] + 2 * margin) / length)) + 4
    coeffs = rng.standard_normal((ny, nx))
    # Per axis the squared B3 weights sum to 0.5 at a node and 0.46 mid-way; in 2-D the
    # variance is the product, so unit coefficients give an rms of 0.46-0.5 (0.479 mean).
    scale = rms / 0.479
    return Roughness(coeffs, float(length), (-margin - 1.5 * length, -margin - 1.5 * length), scale)
