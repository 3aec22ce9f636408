"""Plain-text height images: ASCII matrices and XYZ point lists.

A matrix is one image row per line, numbers separated by white space, commas,
semicolons or tabs; its first line is the *top* row (as Gwyddion exports and as the
image is displayed). Heights are nm, or metres when their whole range is below 1e-3.
Lines starting with ``#`` are comments; a Gwyddion-style header gives the size and
units::

    # Width: 3.000 µm
    # Height: 3.000 µm
    # Value units: m

An XYZ file has three columns ``x y z`` on a regular square grid, in nm, or in metres
when the lateral range is below 1e-3 (Gwyddion's SI export); a ``# Units: m|um|nm``
comment states the unit outright.
"""

from __future__ import annotations

import re

import numpy as np

from nanoasm.errors import InputError

from .limits import MAX_PIXELS

#: nm per unit.
UNITS = {"m": 1e9, "mm": 1e6, "um": 1e3, "µm": 1e3, "μm": 1e3, "nm": 1.0, "pm": 1e-3,
         "a": 0.1, "å": 0.1, "angstrom": 0.1}
_SPLIT = re.compile(r"[\s,;]+")
_SIZE = re.compile(r"^#\s*(width|height)\s*:\s*([-+0-9.eE]+)\s*(\S+)?", re.IGNORECASE)
_VALUE_UNIT = re.compile(r"^#\s*(?:value units|z units|units)\s*:\s*(\S+)", re.IGNORECASE)


def _unit(src: str, name: str) -> float:
    u = name.strip().lower()
    if u not in UNITS:
        raise InputError(src, None, f"unknown length unit {name!r} in the header")
    return UNITS[u]


def _rows(text: str, src: str, per_pixel: int = 1) -> tuple[list[list[float]], list[str]]:
    """The numbers of every line, and the comments; at most ``MAX_PIXELS`` pixels of
    ``per_pixel`` numbers each (refused as soon as there are more)."""
    rows, comments = [], []
    count, limit = 0, MAX_PIXELS * per_pixel
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s)
            continue
        try:
            rows.append([float(v) for v in _SPLIT.split(s) if v])
        except ValueError:
            if not rows:                      # a header line without '#'
                comments.append("# " + s)
                continue
            raise InputError(src, f"line {lineno}", "not a list of numbers") from None
        count += len(rows[-1])
        if count > limit:
            raise InputError(src, f"line {lineno}", f"more than {MAX_PIXELS} pixels (MAX_PIXELS, 4096 x 4096); "
                                                    "no more are read")
    if not rows:
        raise InputError(src, None, "no numbers found")
    return rows, comments


def parse_matrix(text: str, src: str, pixel_size: float | None) -> tuple[np.ndarray, float]:
    """Heights (nm, row 0 at the bottom) and pixel size (nm) of an ASCII matrix."""
    rows, comments = _rows(text, src)
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise InputError(src, None, f"rows have different numbers of values ({min(widths)} to {max(widths)})")
    z = np.array(rows, dtype=float)
    scale, width = None, None
    for c in comments:
        m = _SIZE.match(c)
        if m and m.group(1).lower() == "width":
            width = float(m.group(2)) * _unit(src, m.group(3) or "nm")
        m = _VALUE_UNIT.match(c)
        if m:
            scale = _unit(src, m.group(1))
    if scale is None:
        finite = z[np.isfinite(z)]
        span = float(np.ptp(finite)) if finite.size else 0.0
        scale = 1e9 if 0 < span < 1e-3 else 1.0
    if pixel_size is None:
        if width is None:
            raise InputError(src, "pixel_size", "the file gives no size: pass the pixel size (--pixel-size)")
        pixel_size = width / z.shape[1]
    return np.flipud(z * scale), pixel_size


def parse_xyz(text: str, src: str, pixel_size: float | None
              ) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Heights (nm, row 0 at the bottom), pixel size and origin (nm) of an XYZ list."""
    rows, comments = _rows(text, src, per_pixel=3)
    if {len(r) for r in rows} != {3}:
        raise InputError(src, None, "an XYZ file needs exactly three numbers per line")
    pts = np.array(rows, dtype=float)
    if not np.all(np.isfinite(pts[:, :2])):
        raise InputError(src, None, "x and y must be finite")
    scale = None
    for c in comments:
        m = _VALUE_UNIT.match(c)
        if m:
            scale = _unit(src, m.group(1))
    if scale is None:
        span = np.ptp(pts[:, :2], axis=0).max()
        scale = 1e9 if 0 < span < 1e-3 else 1.0
    pts = pts * scale
    xs, xi = np.unique(pts[:, 0], return_inverse=True)
    ys, yi = np.unique(pts[:, 1], return_inverse=True)
    if xs.size < 2 or ys.size < 2:
        raise InputError(src, None, "XYZ points must span at least 2 x 2 grid positions")
    if xs.size * ys.size != len(pts):
        raise InputError(src, None, f"{len(pts)} points do not fill a regular {xs.size} x {ys.size} grid")
    dx, dy = np.diff(xs), np.diff(ys)
    step = dx.mean()
    tol = 1e-3 * step
    if np.ptp(dx) > tol or np.ptp(dy) > tol or abs(dy.mean() - step) > tol:
        raise InputError(src, None, "XYZ points are not on a regular grid of square pixels")
    if np.unique(yi * xs.size + xi).size != len(pts):
        raise InputError(src, None, "XYZ points repeat a grid position")
    z = np.full((ys.size, xs.size), np.nan)
    z[yi, xi] = pts[:, 2]
    ps = step if pixel_size is None else pixel_size
    return z, ps, (float(xs[0] - ps / 2), float(ys[0] - ps / 2))
