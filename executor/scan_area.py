"""The first full scan's square: where on the scanner it lies and how many pixels a side.

By default a run scans the square on the layout's longer side, centred in the scanner's
XY range, at :attr:`~.strategy.ExecOptions.pixel_size` (:meth:`ScanArea.centred`);
``--region X0 Y0 X1 Y1`` and ``--pixels N`` choose another (:func:`scan_area`). The
square's lower-left corner is the layout frame's origin. Like every instrument's
``full_scan``, a region that is not square is scanned as the square on its longer side
at its lower-left corner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from nanoasm.cad.layout import Layout
from nanoasm.errors import InputError

#: Fewest and most pixels a side of a full scan (most: :data:`nanoasm.world.limits.MAX_PIXELS`).
MIN_PIXELS, MAX_PIXELS = 16, 4096


@dataclass(frozen=True)
class ScanArea:
    """The full scan: its square's lower-left corner in the scanner frame and side (nm),
    the pixels a side, and the resolution registration works at (nm)."""

    origin: tuple[float, float]
    side: float
    pixels: int
    resolution: float

    @classmethod
    def centred(cls, layout_area, xy_range, pixel_size: float) -> ScanArea:
        """Today's full scan: the square on the layout's longer side, centred in the range."""
        side = max(layout_area)
        return cls((0.5 * (xy_range[0] - side), 0.5 * (xy_range[1] - side)), side,
                   int(math.ceil(side / pixel_size)), pixel_size)

    @property
    def region(self) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)``, the instrument's ``full_scan`` region."""
        x, y = self.origin
        return (float(x), float(y), float(x + self.side), float(y + self.side))

    @property
    def pixel_size(self) -> float:
        return self.side / self.pixels


def scan_area(region, pixels: int | None, layout: Layout, xy_range, pixel_size: float, *,
              names: tuple[str, str] = ("--region", "--pixels")) -> ScanArea | None:
    """The full scan of ``layout`` that ``region`` (``(x0, y0, x1, y1)``, scanner frame, nm)
    and ``pixels`` ask for, or None when neither is given (then the run scans as it
    always did).

    Refused in one line naming the option (``names``): a region of no size, one whose
    square leaves the scanner's ``xy_range`` or does not hold the layout's area, a pixel
    count outside ``MIN_PIXELS``..``MAX_PIXELS`` (for a region alone, at ``pixel_size``),
    pixels coarser than half the smallest slot's diameter (its objects would be a pixel
    or two wide)."""
    area = _area(region, pixels, layout.area, xy_range, pixel_size, names)
    finest = min((t.diameter for t in layout.targets), default=math.inf)
    if area is not None and area.pixel_size > finest / 2:
        need = int(math.ceil(area.side / (finest / 2)))
        raise InputError(None, names[1], f"{area.pixels} pixels over {area.side:g} nm are {area.pixel_size:.3g} nm "
                                         f"each, too coarse for the layout's {finest:g} nm objects (at least "
                                         f"{need} pixels)")
    return area


def _area(region, pixels, layout_area, xy_range, pixel_size, names) -> ScanArea | None:
    if region is None and pixels is None:
        return None
    if pixels is not None and not MIN_PIXELS <= pixels <= MAX_PIXELS:
        raise InputError(None, names[1], f"must be from {MIN_PIXELS} to {MAX_PIXELS} pixels a side, got {pixels}")
    if region is None:
        area = ScanArea.centred(layout_area, xy_range, pixel_size)
        return ScanArea(area.origin, area.side, pixels, area.side / pixels)
    x0, y0, x1, y1 = (float(v) for v in region)
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise InputError(None, names[0], "X0 Y0 X1 Y1 must be finite numbers (nm)")
    if not (x1 > x0 and y1 > y0):
        raise InputError(None, names[0], f"must have a positive size (X1 > X0 and Y1 > Y0), got "
                                         f"{x1 - x0:g} x {y1 - y0:g} nm")
    side = max(x1 - x0, y1 - y0)
    xr, yr = xy_range
    if x0 < 0 or y0 < 0 or x0 + side > xr or y0 + side > yr:
        raise InputError(None, names[0], f"the full scan, the {side:g} nm square at ({x0:g}, {y0:g}), leaves the "
                                         f"scanner's XY range 0..{xr:g} x 0..{yr:g} nm")
    if side < max(layout_area):
        raise InputError(None, names[0], f"the {side:g} nm square does not hold the layout's area "
                                         f"{layout_area[0]:g} x {layout_area[1]:g} nm (its origin is the "
                                         f"region's lower-left corner)")
    if pixels is None:
        pixels = int(math.ceil(side / pixel_size))
        if pixels > MAX_PIXELS:
            raise InputError(None, names[0], f"a {side:g} nm square at {pixel_size:g} nm a pixel needs {pixels} "
                                             f"pixels a side, more than {MAX_PIXELS}: give {names[1]}")
    return ScanArea((x0, y0), side, pixels, side / pixels)
