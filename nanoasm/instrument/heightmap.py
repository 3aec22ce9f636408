"""Height images: the one in-memory form of every AFM topography, real or simulated."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from nanoasm.schema import Point


@dataclass(frozen=True, eq=False)
class HeightImage:
    """A topography image in nanometres.

    Parameters
    ----------
    height : (ny, nx) float array
        Heights in nm. Row 0 is the *bottom* row (y up, as the layout frame); readers of
        files stored top-row-first flip them.
    pixel_size : float
        Pixel pitch in nm (square pixels).
    origin : (x, y)
        Position in nm of the lower-left corner of pixel (0, 0). Pixel (i, j) covers
        ``x in origin[0] + [j, j+1) * pixel_size`` and ``y in origin[1] + [i, i+1) * pixel_size``;
        its centre is at ``origin + (j + 0.5, i + 0.5) * pixel_size``.
    source : str
        Where it came from (file name, or ``"simulated"``).
    """

    height: np.ndarray
    pixel_size: float
    origin: Point = (0.0, 0.0)
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        h = np.asarray(self.height, dtype=float)
        if h.ndim != 2 or min(h.shape) < 2:
            raise ValueError(f"height must be a 2-D array of at least 2x2, got shape {h.shape}")
        if not (math.isfinite(self.pixel_size) and self.pixel_size > 0):
            raise ValueError(f"pixel_size must be positive and finite, got {self.pixel_size}")
        object.__setattr__(self, "height", h)

    @property
    def shape(self) -> tuple[int, int]:
        return self.height.shape  # type: ignore[return-value]

    @property
    def extent(self) -> Point:
        """Width and height of the imaged area in nm."""
        ny, nx = self.shape
        return nx * self.pixel_size, ny * self.pixel_size

    def pixel_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """x of each column and y of each row (pixel centres), in nm."""
        ny, nx = self.shape
        x = self.origin[0] + (np.arange(nx) + 0.5) * self.pixel_size
        y = self.origin[1] + (np.arange(ny) + 0.5) * self.pixel_size
        return x, y
