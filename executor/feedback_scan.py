"""DAC paths for scans under the AFM controller's Z feedback, and their height binning.

A hardware backend scans as the seed's local scan does (5.4): the controller holds Z
in tapping-mode feedback, the DAQ drives XY along the line and samples the
controller's height signal on every DAC sample. Z is commanded to the surface
(``z = 0`` nm, the engage setpoint) while engaged and to ``lift`` (or higher) for travel.
Every function returns ``(m, 3)`` int64 DAC codes that continue from a given sample
within the slew limit; none of them sends anything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.instrument import InstrumentConfig, ramp


def z_code(config: InstrumentConfig, z: float) -> int:
    """DAC code of height ``z`` nm in the scanner frame."""
    return int(config.nm_to_codes(np.array([0.0, 0.0, z]))[2])


def xy_code(config: InstrumentConfig, xy, z: float = 0.0) -> np.ndarray:
    """``(3,)`` codes of scanner-frame point ``xy`` (nm) at height ``z`` nm."""
    return config.nm_to_codes(np.array([xy[0], xy[1], z], float))


def straight(a: np.ndarray, b: np.ndarray, config: InstrumentConfig, speed: float,
             min_steps: int = 1) -> np.ndarray:
    """Codes from ``a`` (excluded) to ``b`` (included) in at least ``min_steps`` equal steps,
    at most ``speed`` nm/s."""
    a = np.asarray(a, np.int64)
    b = np.asarray(b, np.int64)
    d = (b - a) * config.nm_per_code
    length = max(math.hypot(d[0], d[1]), abs(d[2]))
    m = max(math.ceil(length / (min(speed, config.max_speed) / config.sample_rate) - 1e-9), int(min_steps))
    k = np.arange(1, m + 1)[:, None] / m
    return np.rint(a + k * (b - a)).astype(np.int64)


def hold(code: np.ndarray, n: int) -> np.ndarray:
    """``n`` copies of one sample."""
    return np.repeat(np.asarray(code, np.int64).reshape(1, 3), int(n), axis=0)


def lift_in_place(config: InstrumentConfig, start: np.ndarray) -> np.ndarray:
    """Raise Z to at least ``lift`` above the surface without moving XY."""
    up = np.array(start, np.int64)
    up[2] = max(up[2], z_code(config, config.lift))
    return ramp(start, up, config)


def travel(config: InstrumentConfig, start: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Lift in place, move XY lifted, then move Z to the target's: the way to any sample."""
    up = lift_in_place(config, start)
    top = up[-1] if up.shape[0] else np.asarray(start, np.int64)
    over = np.array([target[0], target[1], top[2]], np.int64)
    return np.vstack([up, ramp(top, over, config), ramp(over, target, config)])


def park_path(config: InstrumentConfig, start: np.ndarray) -> np.ndarray:
    """Z to the top of its range in place, then XY to rest: :meth:`InstrumentConfig.rest_codes`."""
    rest = config.rest_codes()
    up = np.array(start, np.int64)
    up[2] = rest[2]
    return np.vstack([ramp(start, up, config), ramp(up, rest, config)])


def bin_mean(values: np.ndarray, bins: np.ndarray, n: int) -> np.ndarray:
    """Mean of ``values`` per bin ``0 .. n-1``; an empty bin takes its neighbours' line."""
    counts = np.bincount(bins, minlength=n)[:n]
    sums = np.bincount(bins, weights=values, minlength=n)[:n]
    full = counts > 0
    out = np.empty(n)
    out[full] = sums[full] / counts[full]
    if not full.all():
        idx = np.arange(n)
        out[~full] = np.interp(idx[~full], idx[full], out[full])
    return out


@dataclass(frozen=True, eq=False)
class LinePlan:
    """The samples of one scan line: ``codes`` to stream, ``line`` the slice of them
    sampled along the line, ``bins`` the output point (0 .. n-1) of each."""

    codes: np.ndarray
    line: slice
    bins: np.ndarray


def scan_line_plan(config: InstrumentConfig, start: np.ndarray, a, b, n: int, speed: float,
                   settle: int) -> LinePlan:
    """Travel lifted to ``a``, engage, hold ``settle`` samples (at least one), scan to
    ``b`` at ``speed`` nm/s and lift in place; ``n`` output points from ``a`` to ``b``."""
    pa, pb = xy_code(config, a), xy_code(config, b)
    head = np.vstack([travel(config, start, pa), hold(pa, max(1, settle))])
    line = straight(pa, pb, config, speed, n - 1)
    m = line.shape[0]
    bins = np.rint(np.arange(m + 1) * (n - 1) / m).astype(np.int64)
    codes = np.vstack([head, line, lift_in_place(config, pb)])
    i0 = head.shape[0] - 1  # the last settle sample, at a: k = 0
    return LinePlan(codes, slice(i0, i0 + m + 1), bins)


@dataclass(frozen=True)
class Raster:
    """A ``pixels`` x ``pixels`` raster of the square of side ``side`` nm at ``(x0, y0)``:
    row ``i`` is traced at ``y0 + (i + 1/2) side / pixels`` from ``x0`` to ``x0 + side``."""

    config: InstrumentConfig
    x0: float
    y0: float
    side: float
    pixels: int
    speed: float

    @property
    def pixel_size(self) -> float:
        return self.side / self.pixels

    def row_start(self, i: int) -> np.ndarray:
        return xy_code(self.config, (self.x0, self.y0 + (i + 0.5) * self.pixel_size))

    def approach(self, start: np.ndarray, settle: int) -> np.ndarray:
        """From ``start`` to the first row's start, engaged, then ``settle`` samples held."""
        r0 = self.row_start(0)
        return np.vstack([travel(self.config, start, r0), hold(r0, max(1, settle))])

    def row(self, i: int) -> LinePlan:
        """Trace row ``i`` (sampled), retrace it, step to row ``i + 1`` if there is one."""
        r = self.row_start(i)
        e = xy_code(self.config, (self.x0 + self.side, self.y0 + (i + 0.5) * self.pixel_size))
        trace = straight(r, e, self.config, self.speed, 2 * self.pixels)
        m = trace.shape[0]
        back = straight(e, r, self.config, self.speed)
        parts = [trace, back]
        if i + 1 < self.pixels:
            parts.append(straight(r, self.row_start(i + 1), self.config, self.speed))
        bins = np.minimum(np.arange(1, m + 1) * self.pixels // m, self.pixels - 1)
        return LinePlan(np.vstack(parts), slice(0, m), bins)
