"""Local scan lines: options, requests, results, the seed's line lengths.

A local scan pattern (:mod:`nanoasm.executor.local_scan`) asks for :class:`ScanLine`
requests, one at a time, and gets back a height profile for each; it ends with a
:class:`LocalScanResult`. This module holds those value types, the line-length
conditions of the seed (ch. 5) and the plane geometry the patterns share; the fit of a
rod's outline to the edge crossings is :mod:`nanoasm.executor.capsule_fit`. Lengths in
nm, angles in degrees.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Generator
from dataclasses import dataclass, replace

import numpy as np

from nanoasm.bodies import Body
from nanoasm.param import ParamError, number, param, validate

from .edges import TALLER, Edges, find_edges

#: Fewest samples on a scan line.
MIN_SAMPLES = 11
#: A line whose peak reaches this fraction of the object's height passed close to its
#: centre (particle) or crossed its axis (rod); a lower one grazed the object's rim.
AXIS_PEAK = 0.85


def point(name: str, value) -> np.ndarray:
    """``value`` as a finite (2,) float array, or ValueError naming ``name``."""
    p = np.asarray(value, dtype=float)
    if p.shape != (2,) or not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be two finite numbers, got {value!r}")
    return p


def unit(name: str, value) -> np.ndarray:
    """``value`` normalised to a unit (2,) vector, or ValueError naming ``name``."""
    v = point(name, value)
    norm = math.hypot(*v)
    if not norm > 0:
        raise ValueError(f"{name} must be a non-zero direction, got {value!r}")
    return v / norm


def perp(u: np.ndarray) -> np.ndarray:
    """``u`` turned by +90°."""
    return np.array([-u[1], u[0]])


def wedge(a: np.ndarray, b: np.ndarray) -> float:
    """z-component of the cross product of two (2,) vectors."""
    return float(a[0] * b[1] - a[1] * b[0])


def axis(angle_deg: float) -> np.ndarray:
    t = math.radians(angle_deg)
    return np.array([math.cos(t), math.sin(t)])


# ---------------------------------------------------------------- options and lengths

@dataclass(frozen=True)
class ScanOptions:
    """Knobs of every local scan pattern (the speed-versus-accuracy benchmark turns them).

    Attributes
    ----------
    spacing : float, optional
        Distance between samples on a line (nm); ``min(1, R / 10)`` for an object of
        radius ``R`` when not given.
    margin : float, optional
        Extra line beyond the seed's minimum at each end (nm), room for the tip's
        broadening and for substrate samples to level the line; ``d / 2 + 10 * spacing``
        for an object of diameter ``d`` when not given.
    fraction : float
        Edge level as a fraction of the object's height (see :func:`find_edges`).
    height : float, optional
        Expected object height above the substrate (nm); its diameter when not given.
    noise_rms : float, optional
        Height noise of a line (nm); estimated from each profile when not given.
    max_lines : int
        Most lines one search may use; it then reports "not found".
    length_tolerance : float
        A rod outline whose length differs from the believed length by more than this
        fraction of it (or by more than one diameter, whichever is larger) is refused:
        the lines did not cross the rod as the pattern assumed.
    taller : float, optional
        A bump on a line higher than this share of ``height`` (plus three noise) is
        another object and never taken for the one looked for (see
        :func:`~.edges.find_edges`); None takes any bump.
    rod_height : float, optional
        A rod pattern's cross line is the rod only if its summit is at most this share
        above the rod's believed diameter (plus three noise; see
        :mod:`~.rod_scan`); None allows up to ``taller``. A check scan, which looks for
        any rod its slot takes, uses the slot's size tolerance.
    """

    spacing: float | None = param(None, "nm", "distance between samples on a line (None: min(1, R / 10))",
                                  optional=True, positive=True)
    margin: float | None = param(None, "nm", "extra line beyond the seed's minimum at each end "
                                 "(None: d / 2 + 10 spacing)", optional=True, nonnegative=True)
    fraction: float = param(0.5, "-", "edge level as a fraction of the object's height, in (0, 1)",
                            positive=True)
    height: float | None = param(None, "nm", "expected object height (None: its diameter)",
                                 optional=True, positive=True)
    noise_rms: float | None = param(None, "nm", "height noise of a line (None: estimated)",
                                    optional=True, nonnegative=True)
    max_lines: int = param(64, "-", "most lines one search may use", lo=2)
    length_tolerance: float = param(0.2, "-", "largest relative misfit of a rod outline's length",
                                    positive=True)
    taller: float | None = param(TALLER, "-", "a bump higher than this share of the expected height "
                                 "is another object (None: any bump)", optional=True, lo=1.0)
    rod_height: float | None = param(0.06, "-", "a rod's cross line reads at most this share above its "
                                     "diameter (None: up to taller)", optional=True, nonnegative=True)

    def __post_init__(self) -> None:
        validate(self)
        if not self.fraction < 1:
            raise ParamError("fraction", f"must be below 1, got {self.fraction!r}")

    def resolved(self, diameter: float) -> ScanOptions:
        """These options with every default filled in for an object of ``diameter`` (the
        same options, frozen, for as long as they and the diameter are asked for again:
        a run asks about six times a push, each a validation of every field)."""
        d = number("diameter", diameter, positive=True)
        return _resolved(self, d)

    def sampling(self, diameter: float) -> tuple[float, float]:
        """``(spacing, margin)`` (nm) of :meth:`resolved` for an object of ``diameter``,
        without making the options (choosing among a thousand references)."""
        spacing = self.spacing if self.spacing is not None else min(1.0, diameter / 20)
        return spacing, self.margin if self.margin is not None else diameter / 2 + 10 * spacing


@functools.lru_cache(maxsize=1024)
def _resolved(opts: ScanOptions, d: float) -> ScanOptions:
    spacing, margin = opts.sampling(d)
    height = opts.height if opts.height is not None else d
    return replace(opts, spacing=spacing, margin=margin, height=height)


#: The options every pattern uses unless given others.
DEFAULT_OPTIONS = ScanOptions()


def line_length(kind: str, diameter: float, r_max: float, *, push_length: float = 0.0,
                margin: float = 0.0) -> float:
    """Length of a local scan line by the seed's conditions (ch. 5), plus margins.

    The seed sizes the lines before a push by ``l > R + r_max`` (particle) and
    ``l > d + r_max`` (rod), and after a push by ``l' > Δ + 2(R + r_max)`` and
    ``l' > Δ + 2(d + r_max)``. Read together, ``R + r_max`` (``d + r_max``) is the
    reach needed on each side of where the object may be: the object's edge lies up
    to its size plus the largest position error ``r_max`` from the believed centre, so
    a line centred there needs that reach on both sides, ``2(R + r_max)``; after a
    push of length Δ the line runs from that reach behind the start to that reach
    beyond the end, ``Δ + 2(R + r_max)``, which is the seed's second condition
    literally. Both reduce to one rule::

        length = push_length + 2 (reach + r_max + margin),  reach = R or d

    Parameters
    ----------
    kind : {"particle", "rod"}
    diameter : float
        The object's diameter (nm): R = diameter / 2 for a particle, d = diameter for a rod.
    r_max : float
        Largest expected position error (nm), e.g. :meth:`DriftFilter.r_max`.
    push_length : float
        Δ, the length of the push just made (0 before a push).
    margin : float
        Extra length at each end (0: the seed's bound itself).
    """
    if kind not in ("particle", "rod"):
        raise ValueError(f"kind must be 'particle' or 'rod', got {kind!r}")
    d = number("diameter", diameter, positive=True)
    r_max = number("r_max", r_max, nonnegative=True)
    push_length = number("push_length", push_length, nonnegative=True)
    margin = number("margin", margin, nonnegative=True)
    reach = d / 2 if kind == "particle" else d
    return push_length + 2 * (reach + r_max + margin)


def step_offsets(step: float, limit: float, first: float = 0.0):
    """Offsets ``first, first + step, first - step, first + 2 step, ...`` (alternately up
    and down) until the bands of half a step around them cover ``[first - limit, first + limit]``.

    Yields floats; ``limit = 0`` yields ``first`` only.
    """
    step = number("step", step, positive=True)
    limit = number("limit", limit, nonnegative=True)
    yield first
    k_max = math.ceil(max(limit - step / 2, 0.0) / step - 1e-9)
    for k in range(1, k_max + 1):
        yield first + k * step
        yield first - k * step


# ---------------------------------------------------------------- requests and records

@dataclass(frozen=True)
class ScanLine:
    """One scan-line request: ``n`` samples from ``a`` to ``b`` (both included).

    ``role`` names the line after the seed's figures 5.1 and 5.2 (``"L0"``, ``"V"``,
    ``"L'1"``, ...) for the log. Drive it with ``instrument.scan_line(a, b, n)``.
    """

    a: tuple[float, float]
    b: tuple[float, float]
    n: int
    role: str

    @property
    def length(self) -> float:
        return math.hypot(self.b[0] - self.a[0], self.b[1] - self.a[1])

    @property
    def spacing(self) -> float:
        return self.length / (self.n - 1)

    @property
    def direction(self) -> np.ndarray:
        return (np.asarray(self.b) - np.asarray(self.a)) / self.length

    def at(self, s: float) -> np.ndarray:
        """The point ``s`` nm from ``a`` along the line, (2,) array."""
        return np.asarray(self.a) + s * self.direction


def make_line(origin: np.ndarray, u: np.ndarray, s0: float, s1: float, spacing: float,
              role: str) -> ScanLine:
    """The line from ``origin + s0 u`` to ``origin + s1 u`` at about ``spacing`` nm."""
    n = max(math.ceil((s1 - s0) / spacing - 1e-9) + 1, MIN_SAMPLES)
    a, b = origin + s0 * u, origin + s1 * u
    return ScanLine((float(a[0]), float(a[1])), (float(b[0]), float(b[1])), int(n), role)


@dataclass(frozen=True)
class LineOutcome:
    """A scanned line and the edges found on it."""

    line: ScanLine
    edges: Edges

    def crossings(self) -> np.ndarray:
        """The two edge points, (2, 2) array (rows P1, P2), of a line that found the object."""
        return np.array([self.line.at(self.edges.left), self.line.at(self.edges.right)])

    def midpoint(self) -> np.ndarray:
        return self.line.at(self.edges.centre)


def measure_line(line: ScanLine, expected: float, opts: ScanOptions, substrate=None
                 ) -> Generator[ScanLine, np.ndarray, LineOutcome]:
    """Ask for ``line`` (yield it), receive its profile, return the edges on it.

    ``expected`` is where the object should be (nm from ``line.a``); ``opts`` must be
    :meth:`ScanOptions.resolved`; ``substrate``: as :func:`find_edges` takes it. A
    profile of the wrong shape raises ValueError.
    """
    profile = yield line
    z = np.asarray(profile, dtype=float)
    if z.shape != (line.n,):
        raise ValueError(f"profile for line {line.role} must have shape ({line.n},), got {z.shape}")
    edges = find_edges(z, line.length, opts.height, fraction=opts.fraction, expected=expected,
                       noise_rms=opts.noise_rms, taller=opts.taller, substrate=substrate)
    return LineOutcome(line, edges)


def run_pattern(pattern: Generator, scan_line: Callable[[tuple, tuple, int], np.ndarray]):
    """Drive ``pattern`` with ``scan_line(a, b, n)`` (e.g. ``Instrument.scan_line``);
    returns the pattern's result."""
    try:
        line = next(pattern)
        while True:
            line = pattern.send(scan_line(line.a, line.b, line.n))
    except StopIteration as stop:
        return stop.value


class _Accounting:
    lines: tuple[LineOutcome, ...]

    @property
    def n_lines(self) -> int:
        """Lines scanned."""
        return len(self.lines)

    @property
    def total_length(self) -> float:
        """Their total length (nm)."""
        return float(sum(o.line.length for o in self.lines))

    @property
    def samples(self) -> int:
        """Their total number of samples (for instrument-time accounting)."""
        return int(sum(o.line.n for o in self.lines))


@dataclass(frozen=True, eq=False)
class LocalScanResult(_Accounting):
    """Outcome of one local scan pattern.

    Attributes
    ----------
    pattern : str
        ``"particle_before"``, ``"particle_after"``, ``"rod_before"``, ``"rod_after"``,
        ``"lost_particle"``.
    found : bool
    reason : str
        ``"found"``, or why not (search limit, line budget, a line that missed).
    centre : (x, y) or None
        Measured centre (nm, frame of the lines).
    cov : (2, 2) array or None
        Its covariance (nm²) from the sampling, the noise and the edge slopes.
    angle, angle_std : float or None
        Rod axis angle and its 1-σ (degrees); ``angle_std`` is None when the angle was
        not measured but taken from the belief (``rod_before`` by default).
    length, length_std : float or None
        Rod length and its 1-σ (nm).
    lines : tuple of LineOutcome
        Every line scanned, in order.
    line_creep : (k, 2) array or None
        For each line, the creep (nm, at the nominal amplitude) by which the run shifted
        it to compensate for the time since the pattern's first line (see
        :meth:`creep_sensitivity`); None where no creep is modelled.
    """

    pattern: str
    found: bool
    reason: str
    centre: tuple[float, float] | None = None
    cov: np.ndarray | None = None
    angle: float | None = None
    angle_std: float | None = None
    length: float | None = None
    length_std: float | None = None
    lines: tuple[LineOutcome, ...] = ()
    line_creep: np.ndarray | None = None

    def creep_sensitivity(self) -> np.ndarray:
        """How far (nm) the centre moves per unit relative error of the creep amplitude
        that compensated the lines, (2,). A line along ``u`` measures the centre's
        component along ``u``; shifted by ``(1 + ε̂) d`` while the sample crept ``(1 + ε) d``,
        it sees the object ``(ε − ε̂) d`` off, and the centre, fitted from the lines that
        found the object, carries ``(ε − ε̂)`` times the least-squares blend of their
        ``u uᵀ d``. Zero where nothing was compensated."""
        if self.line_creep is None:
            return np.zeros(2)
        A, b = np.zeros((2, 2)), np.zeros(2)
        for outcome, d in zip(self.lines, self.line_creep):
            if outcome.edges.found:
                u = outcome.line.direction
                P = np.outer(u, u)
                A += P
                b += P @ np.asarray(d, float)
        return np.linalg.pinv(A) @ b

    @property
    def std(self) -> float | None:
        """Largest 1-σ of the centre over all directions (nm)."""
        if self.cov is None:
            return None
        return float(math.sqrt(max(np.linalg.eigvalsh(self.cov)[-1], 0.0)))

    @property
    def ends(self) -> np.ndarray | None:
        """The rod's two ends, (2, 2) array, or None."""
        if self.centre is None or self.angle is None or self.length is None:
            return None
        half = 0.5 * self.length * axis(self.angle)
        c = np.asarray(self.centre)
        return np.array([c - half, c + half])

    def body(self, like: Body) -> Body:
        """``like`` moved to the measured pose (and, for a rod, the measured length)."""
        if not self.found:
            raise ValueError(f"{self.pattern}: no measured pose ({self.reason})")
        if like.elongated:
            return replace(like, at=self.centre, angle=self.angle,
                           length=max(self.length, like.diameter))
        return replace(like, at=self.centre)


def missed(pattern: str, reason: str, lines: list[LineOutcome]) -> LocalScanResult:
    return LocalScanResult(pattern, False, reason, lines=tuple(lines))


def frame_cov(u: np.ndarray, std_u: float, std_v: float) -> np.ndarray:
    """Covariance (2, 2) with 1-σ ``std_u`` along unit ``u`` and ``std_v`` across it."""
    v = perp(u)
    return std_u ** 2 * np.outer(u, u) + std_v ** 2 * np.outer(v, v)
