"""Tip moves to a time-optimal, sample-aligned motion profile (pure geometry, no DAC).

A :class:`Move` is a polyline in the layout frame (nm) with a kind: ``"travel"`` runs
lifted at ``lift`` nm above the substrate, ``"push"`` runs in contact at ``-preload``.
:func:`build_path` turns moves into *vertices* ``(x, y, z, f)``: layout-frame XY, Z in
the scanner frame, and ``f`` the fraction of the push load's deflection the lever holds
there (0 lifted, 1 pushing; it grows linearly with penetration while lowering, as the
deflection of a lever pressed on a hard surface follows the piezo). The command at a
vertex is ``(x, y) - f c + drift`` with ``c`` the deflection offset of
:mod:`nanoasm.executor.dac`, so every segment is a straight line in command space too.

:func:`profile` gives each segment a trapezoidal speed profile from rest to rest (stops at
corners) within the speed and acceleration limits, per axis: XY (Euclidean) and Z. Each
segment's duration is stretched to a whole number of sample periods, which scales its
speed by ``1/λ`` and its acceleration by ``1/λ²`` (``λ >= 1``), so every segment starts
and ends exactly on a sample and the sampled first and second differences respect the
limits exactly. :meth:`Profile.sample` evaluates any range of sample indices in closed
form, so a path of any length is streamed chunk by chunk.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

MOVE_KINDS = ("travel", "push")
#: Segment kinds, indexed by the ``kind`` codes of :class:`Path` and of streamed samples.
SEGMENT_KINDS = ("travel", "lower", "push", "lift")
TRAVEL, LOWER, PUSH, LIFT = range(4)


@dataclass(frozen=True, eq=False)
class Move:
    """One tip move: a polyline in the layout frame.

    Parameters
    ----------
    kind : {"travel", "push"}
        Lifted travel or a push in contact.
    points : (K, 2) array_like
        Polyline vertices in nm, layout frame, ``K >= 1``; the tip first goes (straight, at
        the move's height) from wherever it is to ``points[0]``.
    speed : float, optional
        Speed cap in nm/s for this move (a push speed); the scanner's ``max_speed`` applies
        anyway.
    """

    kind: str
    points: np.ndarray
    speed: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in MOVE_KINDS:
            raise ValueError(f"kind must be one of {', '.join(MOVE_KINDS)}; got {self.kind!r}")
        pts = np.array(self.points, dtype=float, copy=True)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] == 0:
            raise ValueError(f"points must be a (K, 2) array with K >= 1, got shape {pts.shape}")
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"points[{i}] = ({pts[i, 0]}, {pts[i, 1]}) is not finite")
        pts.setflags(write=False)
        object.__setattr__(self, "points", pts)
        if self.speed is not None:
            v = float(self.speed)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"speed must be positive and finite, got {self.speed!r}")
            object.__setattr__(self, "speed", v)


def operation(push: Sequence, travel: Sequence | None = None,
              push_speed: float | None = None) -> tuple[Move, ...]:
    """One push operation: travel (lifted) to the push start, lower, push, lift.

    ``push`` is the tip path in contact, ``(K, 2)`` nm in the layout frame (a plan's
    ``tip_path``); ``travel`` optional waypoints ``(J, 2)`` before the push start.
    Lowering at the push start and lifting at its end follow from the move kinds.
    """
    start = np.asarray(push, dtype=float)[:1]
    way = start if travel is None or len(travel) == 0 else np.vstack([np.asarray(travel, float), start])
    return Move("travel", way), Move("push", push, push_speed)


def as_moves(moves: Iterable) -> tuple[Move, ...]:
    """Moves from :class:`Move` objects or ``(kind, points)`` pairs; errors name ``moves[i]``."""
    out = []
    for i, m in enumerate(moves):
        try:
            out.append(m if isinstance(m, Move) else Move(*m))
        except (TypeError, ValueError) as err:
            raise ValueError(f"moves[{i}]: {err}") from None
    if not out:
        raise ValueError("moves must hold at least one move")
    return tuple(out)


@dataclass(frozen=True, eq=False)
class Path:
    """Vertices of the whole tip path and what each segment between them is.

    Attributes
    ----------
    xyzf : (V, 4) ndarray
        Layout-frame x, y (nm), scanner-frame z (nm) and deflection fraction f per vertex.
    kind : (V - 1,) int8 ndarray
        Segment kind, an index into :data:`SEGMENT_KINDS`.
    speed : (V - 1,) ndarray
        Speed cap per segment, nm/s (``inf`` for none).
    origin : (V, 2) int ndarray
        ``(move, point)`` each vertex comes from; ``(-1, -1)`` for the start.
    """

    xyzf: np.ndarray
    kind: np.ndarray
    speed: np.ndarray
    origin: np.ndarray

    def describe(self, i: int, moves: Sequence[Move]) -> str:
        m, p = (int(v) for v in self.origin[i])
        if m < 0:
            return "the start (the instrument's current position)"
        x, y = moves[m].points[p]
        return f"moves[{m}] ({moves[m].kind}) point {p} at ({x:.1f}, {y:.1f}) nm"


class _Builder:
    def __init__(self, xy, z, lift, preload):
        self.rows, self.kinds, self.speeds, self.origin = [(*xy, z, 0.0)], [], [], [(-1, -1)]
        self.lift, self.bottom = lift, -preload
        self.contact = False

    @property
    def xy(self):
        return self.rows[-1][:2]

    def add(self, xy, z, f, kind, speed=math.inf, origin=None):
        self.rows.append((float(xy[0]), float(xy[1]), z, f))
        self.kinds.append(kind)
        self.speeds.append(speed)
        self.origin.append(self.origin[-1] if origin is None else origin)

    def lift_here(self):
        self.add(self.xy, 0.0, 0.0, LIFT)
        self.add(self.xy, self.lift, 0.0, LIFT)
        self.contact = False

    def goto_lifted(self, xy, origin, speed=math.inf):
        if self.contact:
            self.lift_here()
        self.add(xy, self.lift, 0.0, TRAVEL, speed, origin)

    def lower_here(self):
        self.add(self.xy, 0.0, 0.0, LOWER)
        self.add(self.xy, self.bottom, 1.0, LOWER)
        self.contact = True


def build_path(moves: Sequence[Move], start_xy, start_z: float, lift: float, preload: float) -> Path:
    """Vertices for ``moves`` starting at ``start_xy`` (layout frame nm) and ``start_z`` (nm).

    The tip first rises or sinks vertically to ``lift``; a push starting elsewhere than
    the tip is reached lifted, then lowered (at ``points[0]``) to ``-preload``; a push
    starting where the previous push ended continues in contact; the path ends lifted.
    """
    b = _Builder(start_xy, float(start_z), float(lift), float(preload))
    if start_z != lift:
        b.add(b.xy, b.lift, 0.0, TRAVEL)
    for m, move in enumerate(moves):
        pts = move.points
        speed = math.inf if move.speed is None else move.speed
        if move.kind == "travel":
            for p in range(len(pts)):
                b.goto_lifted(pts[p], (m, p), speed)
            continue
        if not (b.contact and np.array_equal(b.xy, pts[0])):
            b.goto_lifted(pts[0], (m, 0))
            b.lower_here()
        for p in range(1, len(pts)):
            b.add(pts[p], b.bottom, 1.0, PUSH, speed, (m, p))
    if b.contact:
        b.lift_here()
    return Path(np.array(b.rows, float), np.array(b.kinds, np.int8), np.array(b.speeds, float),
                np.array(b.origin, np.int64))


@dataclass(frozen=True, eq=False)
class Profile:
    """Rest-to-rest trapezoidal profiles of the non-empty segments, sample-aligned.

    Segment ``j`` moves from ``start[j]`` by ``delta[j]`` (columns x, y, z, f) along
    ``s(τ)``, a trapezoid on ``[0, 1]`` with peak rate ``peak[j]`` (1/s), acceleration
    ``accel[j]`` (1/s²) and duration ``duration[j]`` (s), played ``stretch[j] >= 1``
    times slower over ``count[j]`` samples. ``ends`` is the cumulative sample count;
    ``vertex_sample`` ``(V,)`` the sample index at which each vertex of the path is reached.
    """

    rate: float
    start: np.ndarray
    delta: np.ndarray
    kind: np.ndarray
    peak: np.ndarray
    accel: np.ndarray
    duration: np.ndarray
    stretch: np.ndarray
    count: np.ndarray
    ends: np.ndarray
    vertex_sample: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(self.ends[-1]) if self.ends.size else 0

    def rests(self) -> np.ndarray:
        """Samples (1-based) where XY comes to rest: the last of a travel or a push that
        another kind follows (the tip lowered or lifted there), and the path's last."""
        full = self.count > 0
        kind, ends = self.kind[full], self.ends[full]
        moving = (kind == TRAVEL) | (kind == PUSH)
        return np.append(ends[:-1][moving[:-1] & (kind[1:] != kind[:-1])], ends[-1:]).astype(np.int64)

    def sample(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vertices-space positions ``(n, 4)`` and segment kinds ``(n,)`` at samples ``k``.

        ``k`` are 1-based sample indices (sample ``k`` plays at ``k / rate`` s after the
        start; sample 0 is the start itself), ``1 <= k <= n_samples``.
        """
        j = np.searchsorted(self.ends, k, side="left")
        left = self.ends.take(j) - k  # samples still to go in the segment
        tau = (self.count.take(j) - left) / (self.rate * self.stretch.take(j))
        s = trapezoid(tau, self.peak.take(j), self.accel.take(j), self.duration.take(j))
        s[left == 0] = 1.0
        return self.start.take(j, axis=0) + s[:, None] * self.delta.take(j, axis=0), self.kind.take(j)


def trapezoid(tau: np.ndarray, peak: np.ndarray, accel: np.ndarray, duration: np.ndarray) -> np.ndarray:
    """Progress ``s`` in [0, 1] at time ``tau`` (s) of a rest-to-rest trapezoid over unit length."""
    ta = peak / accel
    rise = 0.5 * accel * tau * tau
    cruise = 0.5 * peak * ta + peak * (tau - ta)
    rest = duration - tau
    fall = 1.0 - 0.5 * accel * rest * rest
    s = np.where(tau < ta, rise, np.where(rest < ta, fall, cruise))
    return np.clip(s, 0.0, 1.0)


def profile(path: Path, offset: np.ndarray, max_speed: float, max_accel: float, rate: float) -> Profile:
    """Sample-aligned trapezoids for every segment of ``path``.

    ``offset`` (2,) nm is the deflection offset ``c``: the command moves by
    ``Δ(x, y) - Δf c`` in XY and ``Δz`` in Z. Along a segment the XY (Euclidean) and Z
    speeds stay within ``min(max_speed, cap)`` nm/s and accelerations within ``max_accel``
    nm/s²; ``rate`` is the sample rate (Hz). Zero-length segments are dropped.
    """
    counts, parts = segment_counts(path, offset, max_speed, max_accel, rate)
    keep = counts > 0
    peak, accel, duration = (a[keep] for a in parts)
    count = counts[keep]
    delta = np.diff(path.xyzf, axis=0)[keep]
    return Profile(rate=float(rate), start=path.xyzf[:-1][keep], delta=delta, kind=path.kind[keep],
                   peak=peak, accel=accel, duration=duration,
                   stretch=count / (duration * rate), count=count, ends=np.cumsum(count),
                   vertex_sample=np.concatenate([[0], np.cumsum(counts)]))


def segment_counts(path: Path, offset: np.ndarray, max_speed: float, max_accel: float,
                   rate: float) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Samples per segment ``(V - 1,)`` (0 for a zero-length one) and each segment's
    trapezoid ``(peak, accel, duration)`` before stretching."""
    d = np.diff(path.xyzf, axis=0)
    dxy = d[:, :2] - d[:, 3:4] * np.asarray(offset, float)[None, :]
    with np.errstate(over="ignore", invalid="ignore"):
        span = np.maximum(np.hypot(dxy[:, 0], dxy[:, 1]), np.abs(d[:, 2]))
        moving = span > 0
        span = np.where(moving, span, 1.0)
        speed = np.minimum(path.speed, max_speed) / span
        accel = max_accel / span
        peak = np.minimum(speed, np.sqrt(accel))
        duration = 1.0 / peak + peak / accel
        steps = np.ceil(duration * rate)
    if not np.all(np.isfinite(steps[moving])):
        raise OverflowError("a segment is too long to time")
    counts = np.where(moving, np.maximum(steps, 1.0), 0.0).astype(np.int64)
    return counts, (peak, accel, duration)
