"""The microscope as the executor sees it: the :class:`Instrument` protocol, its
configuration, and the limit check every DAC sample passes before it leaves the process.

The simulated AFM and every hardware backend implement the same :class:`Instrument`
methods; the executor cannot tell them apart and never reads simulated truth.

Frames and units. The *scanner frame* is the frame of the DAC: x and y in nm from the
lower-left corner of the scanner's travel (``0 <= x <= xy_range[0]``), z in nm above the
substrate surface found at engage (``-z_range/2 <= z <= z_range/2``; positive lifts the
tip, negative presses it into the surface: a preload). Each axis maps affinely to DAC
volts by its calibration ``nm_per_volt`` (volt ``volt_range[0]`` is the axis' lower
end), and volts to unsigned DAC codes ``0 .. 2**dac_bits - 1`` (code 0 is
``volt_range[0]``, the top code ``volt_range[1]``). A chunk is an ``(n, 3)`` integer array
of XYZ codes streamed at ``sample_rate``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from nanoasm.errors import InstrumentLimitError
from nanoasm.param import ParamError, param, validate

from .heightmap import HeightImage

#: A rectangle ``(x0, y0, x1, y1)`` in the scanner frame, nm.
Region = tuple[float, float, float, float]

AXES = ("x", "y", "z")

#: Largest XY or Z travel of a scanner, nm (1 mm; ``xy_range``, ``z_range``). AFM
#: scanners travel 1-150 µm, large flexure stages a few hundred; beyond it, a wrong unit.
MAX_SCANNER_RANGE = 1e6
#: Slowest and fastest DAC sample clock, Hz (``sample_rate``; the default 1 kHz, the
#: bundled NI card's 10 kHz). Below 100 Hz a sample steps the tip by 500 nm at the default
#: slew limit; above 100 kHz a sample's step (0.5 nm) is far below a DAC code (1.4 nm at
#: 16 bits over 90 µm) and buys nothing, while every sample is computed, streamed and
#: simulated: a dry-run at 100 kHz takes 34 s where 1 kHz takes 2, and at 1 GHz one travel
#: is 44 million samples (1 GB).
MIN_SAMPLE_RATE = 100.0
MAX_SAMPLE_RATE = 100_000.0
#: Slowest and fastest slew limit, nm/s (``max_speed``; the default 50 µm/s): 10 nm/s to
#: 1 mm/s. A slower one makes a travel across the range take days and as many DAC samples
#: (at 1e-300 nm/s, more than memory holds); a faster one is beyond any piezo scanner.
#: The fastest push of a scene (``[timing] push_speed``) is the same.
MIN_SCANNER_SPEED = 10.0
MAX_SCANNER_SPEED = 1e6
#: Smallest and largest scanner calibration, nm per DAC volt (``nm_per_volt``, each axis;
#: the default 4500 XY, 250 Z): 0.1 nm/V to 1 mm/V. Beyond them converting a position
#: to volts underflows or overflows (1e-320 nm/V made every position infinite volts).
MIN_NM_PER_VOLT = 0.1
MAX_NM_PER_VOLT = 1e6


@dataclass(frozen=True)
class InstrumentConfig:
    """Range, calibration, DAC and motion limits of a scanner: the `[scanner]` table.

    Defaults are the seed's instrument (Veeco Bioscope: 90 x 90 µm XY, 5 µm Z; ch. 2.4
    and 3.2) driven full-range by a ±10 V DAC; the rest are realistic values, noted.
    """

    xy_range: tuple[float, float] = param(
        (90000.0, 90000.0), "nm", "XY travel of the scanner", source="seed 2.4, 3.2", positive=True,
        hi=MAX_SCANNER_RANGE)
    z_range: float = param(5000.0, "nm", "Z travel of the scanner", source="seed 2.4, 3.2", positive=True,
                           hi=MAX_SCANNER_RANGE)
    nm_per_volt: tuple[float, float, float] = param(
        (4500.0, 4500.0, 250.0), "nm/V", "scanner calibration per axis (XYZ): travel per DAC volt",
        source="range over the ±10 V span", positive=True, lo=MIN_NM_PER_VOLT, hi=MAX_NM_PER_VOLT)
    dac_bits: int = param(16, "bits", "DAC resolution; 1.37 nm per code in XY at the defaults",
                          source="typical DAQ card; the seed does not give it", lo=8, hi=32)
    volt_range: tuple[float, float] = param(
        (-10.0, 10.0), "V", "DAC output span [low, high]", source="±10 V, seed 3.6.4")
    sample_rate: float = param(1000.0, "Hz", "DAC sample rate of streamed chunks",
                               source="1 kHz haptic/real-time loop; not in the seed", positive=True,
                               lo=MIN_SAMPLE_RATE, hi=MAX_SAMPLE_RATE)
    max_speed: float = param(50000.0, "nm/s", "slew limit, XY (Euclidean) and Z",
                             source="realistic for a 90 µm piezo tube", positive=True,
                             lo=MIN_SCANNER_SPEED, hi=MAX_SCANNER_SPEED)
    max_accel: float = param(1.0e6, "nm/s²", "acceleration limit for trajectory shaping; not checked "
                             "per sample, where DAC quantisation alone exceeds it", positive=True)
    lift: float = param(300.0, "nm", "Z above the substrate for travel; clears objects up to ~150 nm",
                        positive=True)
    preload: float = param(100.0, "nm", "Z below the substrate while pushing: the preload deflection, "
                           "1.1 V of S_n at K_n = 89 nm/V, 12 nN at 0.12 N/m",
                           source="value not in the seed; 3.7 on why to preload",
                           nonnegative=True)
    scan_angle: float = param(0.0, "deg", "scan angle ψ of R(ψ), eq. 3.7", source="seed 3.6.4 uses 0°",
                              lo=-360.0, hi=360.0)

    def __post_init__(self) -> None:
        validate(self)
        lo, hi = self.volt_range
        if not lo < hi:
            raise ParamError("volt_range", f"low end must be below the high end, got [{lo:g}, {hi:g}]")
        if not self.lift < self.z_range / 2:
            raise ParamError("lift", f"must be below the top of the Z range ({self.z_range / 2:g} nm)")
        if not self.preload < self.z_range / 2:
            raise ParamError("preload", f"must be above the bottom of the Z range (-{self.z_range / 2:g} nm)")

    # -- frames and conversions -----------------------------------------------------------
    @property
    def lower(self) -> np.ndarray:
        """Lower end of each axis in nm, (3,)."""
        return np.array([0.0, 0.0, -self.z_range / 2])

    @property
    def upper(self) -> np.ndarray:
        """Upper end of each axis in nm, (3,)."""
        return np.array([self.xy_range[0], self.xy_range[1], self.z_range / 2])

    @property
    def max_code(self) -> int:
        return 2 ** self.dac_bits - 1

    @property
    def volts_per_code(self) -> float:
        return (self.volt_range[1] - self.volt_range[0]) / self.max_code

    @property
    def nm_per_code(self) -> np.ndarray:
        """Quantisation step of each axis in nm, (3,)."""
        return np.asarray(self.nm_per_volt) * self.volts_per_code

    @property
    def max_step(self) -> float:
        """Largest move between consecutive samples in nm (XY norm, or Z)."""
        return self.max_speed / self.sample_rate

    def nm_to_volts(self, nm: np.ndarray) -> np.ndarray:
        """``(..., 3)`` scanner-frame nm to DAC volts."""
        return (np.asarray(nm, float) - self.lower) / np.asarray(self.nm_per_volt) + self.volt_range[0]

    def volts_to_nm(self, volts: np.ndarray) -> np.ndarray:
        return (np.asarray(volts, float) - self.volt_range[0]) * np.asarray(self.nm_per_volt) + self.lower

    def volts_to_codes(self, volts: np.ndarray) -> np.ndarray:
        """Nearest DAC codes (int64); raises InstrumentLimitError on NaN or infinity."""
        v = np.asarray(volts, float)
        if not np.all(np.isfinite(v)):
            raise InstrumentLimitError("non-finite value converted to DAC codes")
        return np.rint((v - self.volt_range[0]) / self.volts_per_code).astype(np.int64)

    def codes_to_volts(self, codes: np.ndarray) -> np.ndarray:
        return np.asarray(codes, float) * self.volts_per_code + self.volt_range[0]

    def nm_to_codes(self, nm: np.ndarray) -> np.ndarray:
        """``(..., 3)`` scanner-frame nm to the nearest DAC codes (not range-checked)."""
        return self.volts_to_codes(self.nm_to_volts(nm))

    def codes_to_nm(self, codes: np.ndarray) -> np.ndarray:
        return self.volts_to_nm(self.codes_to_volts(codes))

    def rest_codes(self) -> np.ndarray:
        """The safe rest sample: XY at the centre of the travel, Z at its top (tip lifted)."""
        return self.nm_to_codes(np.array([self.xy_range[0] / 2, self.xy_range[1] / 2, self.upper[2]]))


@dataclass(frozen=True, eq=False)
class SignalBlock:
    """Photodiode signals sampled during one written chunk (volts), one per DAC sample.

    ``t`` is the instrument time of each sample (s); ``s_n`` the normal (deflection)
    signal S_n and ``s_l`` the lateral (twist) signal S_l of eq. 3.3-3.4, uncompensated.
    """

    t: np.ndarray
    s_n: np.ndarray
    s_l: np.ndarray

    def __post_init__(self) -> None:
        arrays = [np.asarray(a, float) for a in (self.t, self.s_n, self.s_l)]
        if any(a.ndim != 1 for a in arrays) or len({a.shape for a in arrays}) != 1:
            raise ValueError("t, s_n and s_l must be 1-D arrays of one length, got shapes "
                             + ", ".join(str(a.shape) for a in arrays))
        for name, a in zip(("t", "s_n", "s_l"), arrays):
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return self.t.shape[0]


def _as_codes(codes: np.ndarray, label: str = "sample {i}") -> np.ndarray:
    arr = np.asarray(codes)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise InstrumentLimitError(f"a chunk must be an (n, 3) array of XYZ codes with n >= 1, "
                                   f"got shape {arr.shape}")
    if arr.dtype.kind in "iu":
        return arr.astype(np.int64)
    if arr.dtype.kind != "f":
        raise InstrumentLimitError(f"DAC codes must be integers, got dtype {arr.dtype}")
    bad = ~np.isfinite(arr)
    if bad.any():
        i, a = np.argwhere(bad)[0]
        raise InstrumentLimitError(f"{label.format(i=i)}: {AXES[a]} is {arr[i, a]} (NaN or infinite), "
                                   "nothing sent")
    frac = arr != np.rint(arr)
    if frac.any():
        i, a = np.argwhere(frac)[0]
        raise InstrumentLimitError(f"{label.format(i=i)}: {AXES[a]} code {arr[i, a]!r} is not an integer")
    if np.abs(arr).max() > 2.0 ** 62:
        i, a = np.unravel_index(np.abs(arr).argmax(), arr.shape)
        raise InstrumentLimitError(f"{label.format(i=i)}: {AXES[a]} code {arr[i, a]:g} outside the DAC range")
    return arr.astype(np.int64)


def check_samples(codes: np.ndarray, config: InstrumentConfig,
                  previous: np.ndarray | None = None) -> np.ndarray:
    """Validate a chunk of DAC samples; return it as an ``(n, 3)`` int64 array.

    Rejects (raises :class:`~nanoasm.errors.InstrumentLimitError`, naming the first bad
    sample) a chunk with NaN or infinite values, non-integer codes, codes outside
    ``0 .. 2**dac_bits - 1``, positions outside the scanner range, or a step between
    consecutive samples (including ``previous``, the last sample already sent) longer
    than ``max_speed / sample_rate`` in XY (Euclidean) or in Z. A step may exceed that
    length by the quantisation of one code per axis, so a path planned at exactly the
    speed limit passes after rounding.
    """
    c = _as_codes(codes)
    out = (c < 0) | (c > config.max_code)
    if out.any():
        i, a = np.argwhere(out)[0]
        raise InstrumentLimitError(f"sample {i}: {AXES[a]} code {c[i, a]} outside the DAC range "
                                   f"0..{config.max_code}")
    nm = config.codes_to_nm(c)
    tol = 1e-9 * np.maximum(1.0, config.upper - config.lower)
    out = (nm < config.lower - tol) | (nm > config.upper + tol)
    if out.any():
        i, a = np.argwhere(out)[0]
        raise InstrumentLimitError(
            f"sample {i}: {AXES[a]} = {nm[i, a]:.1f} nm outside the scanner range "
            f"[{config.lower[a]:g}, {config.upper[a]:g}] nm")
    _check_slew(c, config, previous)
    return c


def _check_slew(c: np.ndarray, config: InstrumentConfig, previous: np.ndarray | None) -> None:
    start = 0
    if previous is not None:
        prev = np.asarray(previous)
        if prev.size != 3:
            raise InstrumentLimitError(f"previous must be one XYZ sample, got shape {prev.shape}")
        prev = _as_codes(prev.reshape(1, 3), "previous sample")
        c = np.vstack([prev, c])
        start = -1
    if c.shape[0] < 2:
        return
    step = np.diff(c, axis=0) * config.nm_per_code
    q = config.nm_per_code
    xy = np.hypot(step[:, 0], step[:, 1])
    xy_limit = config.max_step + math.hypot(q[0], q[1])
    z_limit = config.max_step + q[2]
    for dist, limit, what in ((xy, xy_limit, "XY"), (np.abs(step[:, 2]), z_limit, "Z")):
        fast = np.flatnonzero(dist > limit * (1 + 1e-12))
        if fast.size:
            k = fast[0]
            a, b = k + start, k + start + 1
            first = "previous sample" if a < 0 else f"sample {a}"
            raise InstrumentLimitError(
                f"{first} -> sample {b}: {what} step {dist[k]:.2f} nm exceeds {config.max_step:.2f} nm "
                f"per sample (max speed {config.max_speed:g} nm/s at {config.sample_rate:g} Hz)")


def ramp(start: np.ndarray, stop: np.ndarray, config: InstrumentConfig,
         speed: float | None = None) -> np.ndarray:
    """Codes that move in a straight line from ``start`` to ``stop`` (both ``(3,)`` codes).

    Moves at ``speed`` (default and at most ``max_speed``) nm/s; the first row is the
    first step after ``start`` and the last row is exactly ``stop``. An empty ``(0, 3)``
    array when they are equal. Used to park and to travel within the slew limit.
    """
    a = np.asarray(start, np.int64).reshape(3)
    b = np.asarray(stop, np.int64).reshape(3)
    v = config.max_speed if speed is None else min(float(speed), config.max_speed)
    if not v > 0:
        raise ValueError(f"speed must be positive, got {speed}")
    d = (b - a) * config.nm_per_code
    length = max(math.hypot(d[0], d[1]), abs(d[2]))
    n = math.ceil(length / (v / config.sample_rate) - 1e-9)
    if n == 0:
        return np.empty((0, 3), np.int64)
    frac = np.arange(1, n + 1)[:, None] / n
    return np.rint(a + frac * (b - a)).astype(np.int64)


@runtime_checkable
class Instrument(Protocol):
    """Everything the executor does to a microscope, and nothing more.

    Implemented by the simulated AFM of :mod:`nanoasm.world.sim` and by each hardware
    backend of :mod:`nanoasm.executor` with the same methods, units and failure modes:
    positions in the scanner frame (nm, see the module docstring), time in instrument
    seconds, signals in volts. A command beyond the limits raises
    :class:`~nanoasm.errors.InstrumentLimitError` before anything is sent.
    """

    @property
    def config(self) -> InstrumentConfig:
        """Range, calibration, DAC and motion limits of this instrument."""
        ...

    def clock(self) -> float:
        """Instrument time in seconds (monotonic; the simulation's own clock)."""
        ...

    def write(self, chunk: np.ndarray) -> SignalBlock:
        """Stream an ``(n, 3)`` int array of XYZ DAC codes at ``config.sample_rate``.

        The chunk is checked with :func:`check_samples` against the last sample sent,
        then played; returns S_n and S_l sampled during it, shape ``(n,)`` each. Contact
        follows from Z: the tip touches the sample where z is at or below the surface.
        """
        ...

    def full_scan(self, pixels: int, region: Region | None = None) -> HeightImage:
        """A ``pixels`` x ``pixels`` tapping-mode topography of ``region`` (scanner frame).

        ``None`` scans the instrument's working area. Takes ``pixels`` lines of
        instrument time; the tip ends lifted.
        """
        ...

    def scan_line(self, a: tuple[float, float], b: tuple[float, float], n: int) -> np.ndarray:
        """Heights (nm, shape ``(n,)``) at ``n`` evenly spaced points from ``a`` to ``b``
        (scanner frame nm, both ends included), in tapping mode; the tip ends lifted."""
        ...

    def signals(self) -> tuple[float, float]:
        """The current photodiode signals ``(S_n, S_l)`` in volts."""
        ...

    def position(self) -> np.ndarray:
        """The DAC's present output, ``(3,)`` int codes: the last sample written, or where
        a scan, a scan line or park left the tip. A stream must start within one slew
        step of it."""
        ...

    def park(self) -> None:
        """Lift the tip and move the DAC to its safe rest value (:meth:`InstrumentConfig.rest_codes`)
        within the slew limit. Safe to call at any time, from any state, repeatedly;
        never raises for a state the instrument is in."""
        ...
