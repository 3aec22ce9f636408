"""Tip moves to checked DAC chunks, streamed lazily with bounded memory.

:func:`plan_dac` validates a whole list of moves up front (every vertex, after drift and
deflection compensation, inside the scanner range; else an
:class:`~nanoasm.errors.InstrumentLimitError` naming the point, before any sample
exists) and times it (:mod:`nanoasm.executor.trajectory`). :meth:`DacPlan.chunks` then
renders samples chunk by chunk through the frame stages of
:mod:`nanoasm.executor.dac_frames`; each chunk passes
:func:`~nanoasm.instrument.check_samples` against the sample before it (the
instrument's current sample for the first) before it is yielded, so no NaN, no
out-of-range code and no over-slew step can leave. Memory is one chunk plus a few
numbers per path vertex, whatever the path's length (chunks are cut from blocks of at
most :data:`BLOCK` samples, or one chunk where chunks are longer).

Typical use by the executor::

    plan = plan_dac(operation(op.tip_path), inst.config, current_codes,
                    t0=inst.clock(), drift=LinearDrift(offset, velocity, t_ref))
    for chunk in plan.chunks(4096):
        signals = inst.write(chunk.codes)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from nanoasm.errors import InstrumentLimitError
from nanoasm.instrument import AXES, InstrumentConfig, check_samples
from nanoasm.world.cantilever import SEED_LEVER, Cantilever

from .dac_frames import (DriftLike, LinearDrift, PushLoad, as_drift, compensate, deflection_offset,
                         drift_at, nm_to_codes, quantisation_error, to_scanner)
from .trajectory import Move, Path, Profile, as_moves, build_path, profile

_DRIFT_GRID = 2049  # times at which a general drift callable's rates are estimated
#: Most samples rendered at once, in whole chunks: a tracked push streams chunks of 100
#: samples, and each stage costs a call per render however few samples it renders.
BLOCK = 4096


@dataclass(frozen=True, eq=False)
class Chunk:
    """Consecutive DAC samples and what they are, for the instrument and the log.

    Attributes
    ----------
    codes : (n, 3) int64 ndarray
        XYZ DAC codes, checked by :func:`~nanoasm.instrument.check_samples`.
    t : (n,) ndarray
        Instrument time of each sample, s.
    nm : (n, 3) ndarray
        Commanded scanner-frame position before rounding, nm.
    kind : (n,) int8 ndarray
        Segment kind per sample, an index into :data:`~nanoasm.executor.trajectory.SEGMENT_KINDS`.
    first : int
        Index of the first sample in the plan (1-based; sample 0 is the start).
    """

    codes: np.ndarray
    t: np.ndarray
    nm: np.ndarray
    kind: np.ndarray
    first: int

    def __len__(self) -> int:
        return self.codes.shape[0]


@dataclass(frozen=True, eq=False)
class DacPlan:
    """A validated, timed path; :meth:`chunks` streams it. Built by :func:`plan_dac`."""

    config: InstrumentConfig
    moves: tuple[Move, ...]
    path: Path
    profile: Profile
    drift: Callable[[np.ndarray], np.ndarray]
    offset: np.ndarray
    current: np.ndarray
    t0: float

    @property
    def n_samples(self) -> int:
        """Number of samples the plan streams (the start sample not counted)."""
        return self.profile.n_samples

    @property
    def duration(self) -> float:
        """Instrument seconds the plan takes to play."""
        return self.n_samples / self.config.sample_rate

    @property
    def quantisation(self) -> np.ndarray:
        """Worst-case DAC rounding error ``(xy, z)`` in nm."""
        return quantisation_error(self.config)

    def render(self, k: np.ndarray) -> Chunk:
        """Samples ``k`` (1-based indices, ``(n,)`` int) through drift, compensation and
        rounding; not slew-checked (:meth:`chunks` checks)."""
        k = np.asarray(k, np.int64)
        pos, kind = self.profile.sample(k)
        t = self.t0 + k / self.config.sample_rate
        xy = to_scanner(pos[:, :2], drift_at(self.drift, t))
        nm = np.column_stack([compensate(xy, pos[:, 3], self.offset), pos[:, 2]])
        return Chunk(nm_to_codes(nm, self.config), t, nm, kind, int(k[0]) if k.size else 1)

    def chunks(self, size: int = 4096) -> Iterator[Chunk]:
        """Checked chunks of at most ``size`` samples, computed lazily, in order.

        Raises :class:`~nanoasm.errors.InstrumentLimitError` (and yields nothing more) if
        a chunk fails :func:`~nanoasm.instrument.check_samples`, which only a
        drift callable misbehaving between its validated values can cause.
        """
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
            raise ValueError(f"size must be a positive integer, got {size!r}")
        return self._chunks(int(size))

    def _chunks(self, size: int) -> Iterator[Chunk]:
        """Chunks cut from blocks of whole chunks up to :data:`BLOCK` samples, each block
        rendered and checked at once (every stage is sample by sample, so a chunk is the
        samples it would be alone); a block that fails is streamed chunk by chunk, so that
        the chunks before the failing one are yielded and its error names it."""
        previous = self.current
        step = size * max(1, BLOCK // size)
        for b in range(1, self.n_samples + 1, step):
            k = np.arange(b, min(b + step, self.n_samples + 1), dtype=np.int64)
            try:
                block = self.render(k)
                check_samples(block.codes, self.config, previous)
            except InstrumentLimitError:
                previous = yield from self._checked(k, size, previous)
                continue
            for a in range(0, k.size, size):
                cut = slice(a, a + size)
                yield Chunk(block.codes[cut], block.t[cut], block.nm[cut], block.kind[cut], b + a)
            previous = block.codes[-1]

    def _checked(self, k: np.ndarray, size: int, previous):
        """Samples ``k`` rendered and checked a chunk at a time; returns the last sample."""
        for a in range(0, k.size, size):
            try:
                chunk = self.render(k[a:a + size])
                check_samples(chunk.codes, self.config, previous)
            except InstrumentLimitError as err:
                raise InstrumentLimitError(f"chunk from sample {int(k[a])}: {err}") from None
            previous = chunk.codes[-1]
            yield chunk
        return previous


def plan_dac(moves: Iterable, config: InstrumentConfig, current, *, t0: float = 0.0,
             drift: DriftLike = None, load: PushLoad | None = None,
             lever: Cantilever = SEED_LEVER, tolerance: float | None = None) -> DacPlan:
    """Validate and time ``moves`` for streaming to the DAC.

    Parameters
    ----------
    moves : iterable of Move or (kind, points)
        Tip moves, layout frame nm (see :func:`~nanoasm.executor.trajectory.operation`).
    config : InstrumentConfig
        Range, calibration, sample rate, ``max_speed`` (nm/s), ``max_accel`` (nm/s²),
        ``lift`` and ``preload`` (nm) and ``scan_angle`` (deg) of the instrument.
    current : (3,) int array_like
        The instrument's current (last written) XYZ codes; the path starts there.
    t0 : float
        Instrument time (s) of ``current``; sample ``k`` plays at ``t0 + k / sample_rate``.
    drift : None, (dx, dy) or callable
        Drift offset in nm, constant or a vectorised function of time ``(n,) -> (n, 2)``.
    load : PushLoad, optional
        Mean compensated signals while pushing; default the preload's
        (:meth:`PushLoad.from_preload`).
    lever : Cantilever
        C1, C2 and K_n of the compensation.
    tolerance : float, optional
        Positioning tolerance, nm: refuse a DAC whose XY rounding error may exceed it.

    Raises
    ------
    ValueError
        Malformed moves, drift, load or parameters (naming them).
    InstrumentLimitError
        A point outside the scanner range after drift and compensation (naming it), a
        drift too fast for the slew limits, quantisation beyond ``tolerance``, or an
        invalid ``current``.
    """
    moves = as_moves(moves)
    if not isinstance(config, InstrumentConfig):
        raise ValueError(f"config must be an InstrumentConfig, got {type(config).__name__}")
    current = _current(current, config)
    t0 = float(t0)
    if not math.isfinite(t0):
        raise ValueError(f"t0 must be finite, got {t0!r}")
    _check_tolerance(config, tolerance)
    drift_fn = as_drift(drift)
    offset = deflection_offset(PushLoad.from_preload(config, lever) if load is None else load,
                               config.scan_angle, lever)
    start = config.codes_to_nm(current)
    path = build_path(moves, start[:2] - drift_at(drift_fn, np.array([t0]))[0], start[2],
                      config.lift, config.preload)
    drift0 = drift_at(drift_fn, np.array([t0]))[0]
    _check_range_coarse(path, moves, offset, drift0, config)
    if isinstance(drift_fn, LinearDrift) and not np.any(drift_fn.velocity):
        # constant drift: the exact check needs no timing, so it comes first
        _check_range_coarse(path, moves, offset, drift0, config, slack=0.0)
    prof = _timed(path, offset, drift_fn, t0, config)
    _check_range(path, moves, prof, offset, drift_fn, t0, config)
    return DacPlan(config, moves, path, prof, drift_fn, offset, current, t0)


def _current(current, config: InstrumentConfig) -> np.ndarray:
    arr = np.asarray(current)
    if arr.shape != (3,):
        raise ValueError(f"current must be one XYZ sample of shape (3,), got shape {arr.shape}")
    return check_samples(arr.reshape(1, 3), config)[0]


def _check_tolerance(config: InstrumentConfig, tolerance: float | None) -> None:
    if tolerance is None:
        return
    tol = float(tolerance)
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tolerance must be positive and finite, got {tolerance!r}")
    q = quantisation_error(config)[0]
    if q > tol:
        raise InstrumentLimitError(
            f"DAC rounding may place the tip {q:.3g} nm off in XY ({config.dac_bits} bits, "
            f"{config.nm_per_code[0]:.3g} nm per code), more than the tolerance {tol:g} nm")


def _commands(path: Path, offset: np.ndarray) -> np.ndarray:
    """Vertex commands ``(V, 3)`` in nm before drift: ``(xy - f c, z)``."""
    v = path.xyzf
    return np.column_stack([v[:, :2] - v[:, 3:4] * offset, v[:, 2]])


def _first_outside(points: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    out = ~((points >= lo) & (points <= hi))
    if not out.any():
        return None
    return tuple(int(v) for v in np.argwhere(out)[0])


def _check_range_coarse(path: Path, moves, offset, drift0, config: InstrumentConfig,
                        slack: float = 1.0) -> None:
    """Refuse points farther outside the range than ``slack`` times the range's own size
    (no plausible drift brings them in) before timing, which such points could overflow.
    With ``slack`` 0 it is the exact check for a constant drift."""
    span = (config.upper - config.lower) * slack
    cmd = _commands(path, offset)
    cmd[:, :2] += drift0
    hit = _first_outside(cmd, config.lower - span, config.upper + span)
    if hit is not None:
        i, a = hit
        far = "far " if slack else ""
        raise InstrumentLimitError(
            f"{path.describe(i, moves)} commands {AXES[a]} = {cmd[i, a]:.6g} nm (drift "
            f"({drift0[0]:+.1f}, {drift0[1]:+.1f}) nm), {far}outside the "
            f"scanner range [{config.lower[a]:g}, {config.upper[a]:g}] nm; nothing sent")


def _timed(path: Path, offset, drift_fn, t0: float, config: InstrumentConfig) -> Profile:
    """Profile within the limits less the drift's own speed and acceleration."""
    if isinstance(drift_fn, LinearDrift):
        rates = (drift_fn.speed, 0.0)
    else:
        first = profile(path, offset, config.max_speed, config.max_accel, config.sample_rate)
        span = 2.0 * (first.n_samples + len(path.kind)) / config.sample_rate
        rates = _drift_rates(drift_fn, t0, t0 + max(span, 1.0 / config.sample_rate))
    speed, accel = config.max_speed - rates[0], config.max_accel - rates[1]
    if not (speed >= config.max_speed / 2 and accel >= config.max_accel / 2):
        raise InstrumentLimitError(
            f"drift of {rates[0]:.3g} nm/s and {rates[1]:.3g} nm/s² leaves less than half of the "
            f"scanner's {config.max_speed:g} nm/s and {config.max_accel:g} nm/s²; nothing sent")
    try:
        return profile(path, offset, speed, accel, config.sample_rate)
    except OverflowError:
        raise InstrumentLimitError("a move is too long or too slow to time in samples; "
                                   "nothing sent") from None


def _drift_rates(drift_fn, t_start: float, t_end: float) -> tuple[float, float]:
    """Largest speed (nm/s) and acceleration (nm/s²) of a drift callable, estimated by
    finite differences on a grid of :data:`_DRIFT_GRID` times over ``[t_start, t_end]``."""
    t = np.linspace(t_start, t_end, _DRIFT_GRID)
    d = drift_at(drift_fn, t)
    h = t[1] - t[0]
    v = np.diff(d, axis=0) / h
    a = np.diff(v, axis=0) / h
    return float(np.hypot(v[:, 0], v[:, 1]).max()), float(np.hypot(a[:, 0], a[:, 1]).max())


def _check_range(path: Path, moves: Sequence[Move], prof: Profile, offset, drift_fn, t0: float,
                 config: InstrumentConfig) -> None:
    """Every vertex command plus the drift at its own and its neighbours' times within
    range: the corners of each segment's sweep, exact for a drift monotone on each axis
    within a segment (constant, linear, creep-like)."""
    cmd = _commands(path, offset)
    d = drift_at(drift_fn, t0 + prof.vertex_sample / config.sample_rate)
    n = len(cmd)
    for shift in (0, -1, 1):
        idx = np.clip(np.arange(n) + shift, 0, n - 1)
        pts = cmd.copy()
        pts[:, :2] += d[idx]
        hit = _first_outside(pts, config.lower, config.upper)
        if hit is not None:
            i, a = hit
            raise InstrumentLimitError(
                f"{path.describe(i, moves)} reaches {AXES[a]} = {pts[i, a]:.1f} nm in the scanner "
                f"frame (drift ({d[idx[i], 0]:+.1f}, {d[idx[i], 1]:+.1f}) nm, deflection "
                f"compensation {path.xyzf[i, 3]:g} x ({-offset[0]:+.1f}, {-offset[1]:+.1f}) nm), "
                f"outside the scanner range [{config.lower[a]:g}, {config.upper[a]:g}] nm; nothing sent")
