"""The arguments of a hardware backend's scans, checked before anything is sent, and the
frame a scan module returns brought to the pixels asked for.

Shared by the hardware backends (:mod:`.nidaq`, :mod:`.nanonis`): a bad argument is a
``ValueError``, a point or square outside the scanner's travel an
:class:`~nanoasm.errors.InstrumentLimitError` saying that nothing was sent.
"""

from __future__ import annotations

import numpy as np

from nanoasm.errors import InstrumentLimitError
from nanoasm.instrument import InstrumentConfig, Region
from nanoasm.param import number


def count(name: str, n) -> int:
    """An integer of at least 2 (pixels, points of a line)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise ValueError(f"{name} must be an integer of at least 2, got {n!r}")
    return int(n)


def scanner_xy(config: InstrumentConfig, name: str, p) -> np.ndarray:
    """``p`` as a ``(2,)`` point (nm) within the scanner's XY travel."""
    try:
        arr = np.asarray(p, float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be two finite numbers, got {p!r}") from None
    if arr.shape != (2,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be two finite numbers, got {p!r}")
    hi = config.upper[:2]
    if np.any(arr < 0) or np.any(arr > hi):
        raise InstrumentLimitError(f"{name} = ({arr[0]:g}, {arr[1]:g}) nm lies outside the scanner "
                                   f"range [0, {hi[0]:g}] x [0, {hi[1]:g}] nm; nothing sent")
    return arr


def scan_square(config: InstrumentConfig, region: Region | None) -> tuple[float, float, float]:
    """``(x0, y0, side)``: the square of side max(width, height) at the region's lower-left
    corner, or the largest square of the XY travel at the origin for ``None``."""
    xr, yr = config.xy_range
    if region is None:
        return 0.0, 0.0, min(xr, yr)
    if len(region) != 4:
        raise ValueError(f"region must be four numbers (x0, y0, x1, y1), got {region!r}")
    x0, y0, x1, y1 = (number(f"region[{i}]", v) for i, v in enumerate(region))
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"region must have x1 > x0 and y1 > y0, got {region!r}")
    side = max(x1 - x0, y1 - y0)
    if x0 < 0 or y0 < 0 or x0 + side > xr or y0 + side > yr:
        raise InstrumentLimitError(f"the {side:g} nm square at ({x0:g}, {y0:g}) leaves the scanner range "
                                   f"[0, {xr:g}] x [0, {yr:g}] nm; nothing sent")
    return x0, y0, side


def resample(frame: np.ndarray, pixels: int) -> np.ndarray:
    """A ``(rows, cols)`` frame linearly resampled to ``pixels`` x ``pixels`` pixel centres."""
    rows, cols = frame.shape
    if (rows, cols) == (pixels, pixels):
        return frame
    u = (np.arange(pixels) + 0.5) / pixels
    cx, cy = u * cols - 0.5, u * rows - 0.5
    by_col = np.array([np.interp(cx, np.arange(cols), r) for r in frame])
    return np.array([np.interp(cy, np.arange(rows), c) for c in by_col.T]).T


__all__ = ["count", "resample", "scan_square", "scanner_xy"]
