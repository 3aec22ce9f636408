"""Calibrating the lever through the instrument itself (seed 3.4-3.6), as a procedure.

:func:`calibrate` is a generator of :class:`~.engine.Msg` run by the
:class:`~.engine.RunEngine` (which parks the tip however it ends), on any
:class:`~nanoasm.instrument.Instrument`: it writes DAC samples and reads the signals they
return, and scans one line, nothing more. Its steps, one event line each:

1. ``force curve``: the piezo ramps down into the substrate at ``sites.substrate`` and
   back; K_n (eq. 3.13) and α (§3.5) from the contact part, the baselines' change from
   the lift height to contact from the approach above it;
2. ``baselines``: S_n and S_l along lifted lines over ``sites.baseline_*``, binned into the
   maps A(i, j), B(i, j) (eq. 3.28-3.29) and brought down to contact by step 1;
3. ``substrate loop``: trace and retrace along ``sites.flat`` at several loads; its
   half-width per volt of S_n is μ_ts k K_n / (k_l K_l / h);
4. ``slope loops``: a scan line along ``sites.slope`` gives the tilt θ; trace (up) and
   retrace (down) with z following it at several loads give (k_l K_l / h, μ) (eq.
   3.26-3.27), and with step 3, μ_ts;
5. ``edge``: the tip slides along ``sites.edge`` onto a step at several loads (in a
   palindromic order, so a steady drift cancels); where it climbs gives C2;
6. C1 = K_n h / l (§3.6.3; ``h`` and ``l`` given, as ``k`` is).

Lengths in the scanner frame (nm), loads as the lever's deflection (nm below the surface).
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from nanoasm.instrument import InstrumentConfig, ramp
from nanoasm.param import ParamError, number
from nanoasm.schema import Point
from nanoasm.world.cantilever import Cantilever, to_afm

from . import calibration_fit as fit
from .baselines import MAX_PIXELS, BaselineMaps
from .calibration_fit import CalibrationFailed, Value
from .engine import Msg

#: Largest angle (deg) between a calibration line and the lever axis it must follow.
MAX_MISALIGN = 10.0
#: Shortest calibration line, nm.
MIN_LINE = 200.0


@dataclass(frozen=True)
class CalibrationSites:
    """Where on the sample the calibration presses and slides (scanner frame, nm): the
    instrument file's ``[calibration]`` table."""

    substrate: Point
    flat: tuple[Point, Point]
    slope: tuple[Point, Point]
    edge: tuple[Point, Point]
    baseline_origin: Point
    baseline_side: float
    baseline_pixels: int = 16

    def check(self, config: InstrumentConfig) -> None:
        """Raise ParamError naming the key of a site outside the scanner or a line that does
        not follow the lever axis it must (the lever's y axis, or its axis for ``edge``)."""
        lo, hi = config.lower[:2], config.upper[:2]
        points = {"substrate": [self.substrate], "flat": self.flat, "slope": self.slope, "edge": self.edge,
                  "baseline_origin": [self.baseline_origin],
                  "baseline_side": [np.add(self.baseline_origin, self.baseline_side)]}
        for key, pts in points.items():
            for p in pts:
                if np.any(np.asarray(p) < lo) or np.any(np.asarray(p) > hi):
                    raise ParamError(key, f"({p[0]:g}, {p[1]:g}) nm lies outside the scanner's XY range")
        if not 2 <= self.baseline_pixels <= MAX_PIXELS:
            raise ParamError("baseline_pixels", f"must be 2-{MAX_PIXELS}, got {self.baseline_pixels}")
        for key, line, axis, name in (("flat", self.flat, 1, "y axis"), ("slope", self.slope, 1, "y axis"),
                                      ("edge", self.edge, 0, "axis")):
            d = np.subtract(line[1], line[0])
            length = float(np.hypot(*d))
            if length < MIN_LINE:
                raise ParamError(key, f"must be at least {MIN_LINE:g} nm long, got {length:.0f}")
            want = to_afm(np.eye(2)[axis], config.scan_angle)
            off = math.degrees(math.acos(min(1.0, abs(float(d @ want)) / length)))
            if off > MAX_MISALIGN:
                raise ParamError(key, f"must run along the lever's {name} (direction ({want[0]:.3g}, "
                                      f"{want[1]:.3g}) at scan_angle {config.scan_angle:g} deg), "
                                      f"{off:.0f} deg off")


@dataclass(frozen=True)
class CalibrationSetup:
    """What the calibration is given (``k``, ``h``, ``l``) and how it measures."""

    spring_constant: float                 # k, N/m (= nN/nm), the maker's or a thermal tune's
    tip_height: float = 3000.0             # h, nm
    length: float = 200_000.0              # l, nm
    depth: float = 300.0                   # force curve: nm below the surface at the bottom
    loads: int = 7                         # loads of each friction loop
    edge_loads: int = 5                    # loads of the edge, each passed twice
    line_speed: float = 1000.0             # nm/s, friction loops
    approach_speed: float = 200.0          # nm/s, z in contact
    edge_speed: float = 100.0              # nm/s, onto the step
    full_scale: float = 10.0               # V, the detector's range (``signal_limit``)

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("loads", "edge_loads"):
                if isinstance(v, bool) or not isinstance(v, int) or v < 3:
                    raise ParamError(f.name, f"must be an integer of at least 3, got {v!r}")
            else:
                number(f.name, v, positive=True)


@dataclass(frozen=True, eq=False)
class Calibration:
    """The calibrated lever: values with uncertainties, the maps, and each step's data."""

    values: dict[str, Value]               # k, K_n, C1, C2, lateral_gain, alpha, mu_ts, mu_slope, tilt
    baselines: BaselineMaps
    given: dict[str, float]                # tip_height, length
    steps: dict[str, dict] = field(default_factory=dict)

    def lever(self, full_scale: float = 10.0) -> Cantilever:
        v = {k: x.value for k, x in self.values.items()}
        return Cantilever(spring_constant=v["k"], normal_gain=v["K_n"], lateral_gain=v["lateral_gain"],
                          tip_height=self.given["tip_height"], lever_length=self.given["length"], c2=v["C2"],
                          c1_override=v["C1"], crosstalk=v["alpha"], full_scale=full_scale)


Procedure = Generator[Msg, Any, Calibration]


class _Tip:
    """Where the DAC is (codes), and the moves that keep within the slew limit."""

    def __init__(self, config: InstrumentConfig, codes):
        self.cfg, self.codes = config, np.asarray(codes)

    def nm(self) -> np.ndarray:
        return self.cfg.codes_to_nm(self.codes)

    def path(self, nm_points: np.ndarray) -> np.ndarray:
        """Codes of samples at scanner nm ``(n, 3)``; becomes the position."""
        codes = self.cfg.nm_to_codes(np.asarray(nm_points, float))
        self.codes = codes[-1]
        return codes

    def to(self, xyz, speed: float | None = None) -> np.ndarray:
        there = self.cfg.nm_to_codes(np.asarray(xyz, float))
        codes = ramp(self.codes, there, self.cfg, speed=speed)
        self.codes = there
        return codes


def _line(a, b, speed: float, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 2) from ``a`` to ``b`` at ``speed`` nm/s (first after ``a``) and their distance from ``a``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.hypot(*(b - a)))
    n = max(2, math.ceil(length / (speed / rate)))
    s = np.arange(1, n + 1) / n * length
    return a + (b - a) * (s / length)[:, None], s


def _write(codes):
    """Play ``codes`` (skipped when empty); returns the SignalBlock or None."""
    if len(codes):
        return (yield Msg("write", (codes,)))
    return None


def _travel(tip: _Tip, xy):
    yield from _write(tip.to((xy[0], xy[1], tip.cfg.lift)))


def _lift(tip: _Tip):
    here = tip.nm()
    yield from _write(tip.to((here[0], here[1], max(here[2], tip.cfg.lift))))


def _force_curve(tip: _Tip, sites: CalibrationSites, setup: CalibrationSetup):
    cfg = tip.cfg
    yield from _travel(tip, sites.substrate)
    x, y = sites.substrate
    down = tip.to((x, y, -setup.depth), speed=setup.approach_speed)
    z = cfg.codes_to_nm(down)[:, 2]
    block = yield from _write(down)
    yield from _write(tip.to((x, y, cfg.lift), speed=setup.approach_speed))
    return fit.force_curve_fit(z, block.s_n, block.s_l, cfg.lift, setup.full_scale), \
        {"z": z, "s_n": block.s_n, "s_l": block.s_l}


def _baselines(tip: _Tip, sites: CalibrationSites, shift: tuple[float, float]):
    """A(i, j), B(i, j) along lifted lines, each row traced and retraced (the piezo's lag
    cancels), binned to the nearest cell: the mean of the two passes' medians."""
    cfg, n = tip.cfg, sites.baseline_pixels
    (x0, y0), side = sites.baseline_origin, sites.baseline_side
    cell = side / (n - 1)
    speed = min(0.2 * cfg.max_speed, cell * cfg.sample_rate / 8.0)     # at least 8 samples a cell
    maps = np.zeros((2, n, n))
    for j in range(n):
        y = y0 + side * (n - 1 - j) / (n - 1)
        yield from _travel(tip, (x0, y))
        for xs in ((x0, x0 + side), (x0 + side, x0)):
            pts, _ = _line((xs[0], y), (xs[1], y), speed, cfg.sample_rate)
            block = yield from _write(tip.path(np.column_stack([pts, np.full(len(pts), cfg.lift)])))
            i = np.clip(np.rint((pts[:, 0] - x0) / cell), 0, n - 1).astype(int)
            for k in range(n):
                sel = i == k
                if not sel.any():
                    raise CalibrationFailed("baselines: a map cell got no sample")
                maps[:, j, k] += 0.5 * np.array([np.median(block.s_n[sel]), np.median(block.s_l[sel])])
    return BaselineMaps((x0, y0), side, maps[0] + shift[0], maps[1] + shift[1]), {"lift_a": maps[0], "lift_b": maps[1]}


def _loops(tip: _Tip, line, loads, setup: CalibrationSetup, profile=None):
    """Trace ``line[0] -> line[1]`` and retrace at each load (nm pressed below the surface,
    whose height along the line is ``profile(s)``, default 0). Per load: mean S_n, and the
    mean S_l of trace and retrace, over the middle 80 % of each pass."""
    cfg = tip.cfg
    a, b = np.asarray(line[0], float), np.asarray(line[1], float)
    prof = profile or (lambda s: np.zeros_like(s))
    pts, s = _line(a, b, setup.line_speed, cfg.sample_rate)
    back, s_back = pts[::-1][1:], s[::-1][1:]
    back, s_back = np.vstack([back, a]), np.append(s_back, 0.0)
    mid = (s > 0.1 * s[-1]) & (s < 0.9 * s[-1])
    mid_back = (s_back > 0.1 * s[-1]) & (s_back < 0.9 * s[-1])
    yield from _travel(tip, a)
    out = np.empty((len(loads), 3))
    for k, d in enumerate(loads):
        yield from _write(tip.to((a[0], a[1], float(prof(np.array([0.0]))[0]) - d), speed=setup.approach_speed))
        trace = yield from _write(tip.path(np.column_stack([pts, prof(s) - d])))
        retrace = yield from _write(tip.path(np.column_stack([back, prof(s_back) - d])))
        out[k] = (0.5 * (trace.s_n[mid].mean() + retrace.s_n[mid_back].mean()), trace.s_l[mid].mean(),
                  retrace.s_l[mid_back].mean())
    yield from _lift(tip)
    return out


def _lateral_sign(line, config: InstrumentConfig) -> float:
    """Cosine between a line and the lever's y axis (±1 for a line along it)."""
    d = np.subtract(line[1], line[0])
    return float(d @ to_afm(np.array([0.0, 1.0]), config.scan_angle) / np.hypot(*d))


def _slope(tip: _Tip, sites: CalibrationSites, loads, setup: CalibrationSetup, alpha: Value):
    cfg = tip.cfg
    a, b = (np.asarray(p, float) for p in sites.slope)
    length = float(np.hypot(*(b - a)))
    heights = yield Msg("scan_line", (tuple(a), tuple(b), 200))
    tip.codes = np.asarray((yield Msg("position")))
    s = np.linspace(0.0, length, len(heights))
    grade, h0 = fit.line_fit(s, heights, "slope profile")
    rms = float(np.std(heights - (h0 + grade.value * s)))
    if rms > 5.0:
        raise CalibrationFailed(f"slope: the scan line is not on a plane ({rms:.1f} nm rms off the best line)")
    if max(heights.max(), h0 + grade.value * length) > cfg.lift - 20.0:
        raise CalibrationFailed(f"slope: the surface rises above the lift height less 20 nm ({cfg.lift:g} nm)")
    tilt = Value(math.degrees(math.atan(abs(grade.value))), math.degrees(grade.sigma / (1 + grade.value ** 2)))
    rows = yield from _loops(tip, (a, b), loads, setup, profile=lambda q: h0 + grade.value * q)
    # S̃ = -S_l / (g·v): the lateral force against the slope per lateral gain (g uphill)
    up_first = grade.value > 0
    g_v = _lateral_sign((a, b), cfg) * (1.0 if up_first else -1.0)
    up_sl, down_sl = (rows[:, 1], rows[:, 2]) if up_first else (rows[:, 2], rows[:, 1])
    slopes = []
    for sl in (down_sl, up_sl):
        raw, _ = fit.line_fit(rows[:, 0], -sl / g_v, "friction loops on the slope")
        slopes.append(Value(raw.value + alpha.value / g_v, math.hypot(raw.sigma, alpha.sigma)))
    return tilt, slopes[0], slopes[1], {"s": s, "heights": heights, "rows": rows, "g_v": g_v}


def _edge(tip: _Tip, sites: CalibrationSites, loads, setup: CalibrationSetup):
    """Per pass: S_n before the step, the piezo's position along the lever axis where the
    tip climbed it, the time then and the load."""
    cfg = tip.cfg
    u = to_afm(np.array([1.0, 0.0]), cfg.scan_angle)
    a, b = (np.asarray(p, float) for p in sites.edge)
    pts, _ = _line(a, b, setup.edge_speed, cfg.sample_rate)
    chunk = max(20, int(0.2 * cfg.sample_rate))
    out = []
    for d in loads:
        yield from _travel(tip, a)
        yield from _write(tip.to((a[0], a[1], -d), speed=setup.approach_speed))
        s_n, xy, ts, hit = [], [], [], None
        for i in range(0, len(pts), chunk):
            part = pts[i:i + chunk]
            codes = tip.path(np.column_stack([part, np.full(len(part), -d)]))
            block = yield from _write(codes)
            s_n.append(block.s_n)
            ts.append(block.t)
            xy.append(cfg.codes_to_nm(codes)[:, :2])
            hit = fit.climb_index(np.concatenate(s_n))
            if hit is not None:
                break
        yield from _lift(tip)
        if hit is None:
            raise CalibrationFailed(f"edge: the tip never climbed a step along the edge line at {d:.0f} nm of load")
        sn = np.concatenate(s_n)
        out.append((float(np.median(sn[max(0, hit - 200):hit])), float(np.concatenate(xy)[hit] @ u),
                    float(np.concatenate(ts)[hit]), d))
    return np.array(out)


def calibrate(sites: CalibrationSites, setup: CalibrationSetup, config: InstrumentConfig) -> Procedure:
    """The calibration procedure (see the module docstring); returns a :class:`Calibration`."""
    tip = _Tip(config, (yield Msg("position")))
    k = setup.spring_constant
    fc, curve = yield from _force_curve(tip, sites, setup)
    k_n = fc.normal_gain
    yield Msg("event", (f"force curve at ({sites.substrate[0]:.0f}, {sites.substrate[1]:.0f}) nm: K_n = "
                        f"{k_n.value:.2f} ± {k_n.sigma:.2f} nm/V (eq. 3.13), alpha = {fc.crosstalk.value:.4f} ± "
                        f"{fc.crosstalk.sigma:.4f} (3.5), surface at z = {fc.contact_z:.1f} nm",))
    maps, lifted = yield from _baselines(tip, sites, (fc.shift_n, fc.shift_l))
    yield Msg("event", (f"baselines: {maps.pixels} x {maps.pixels} maps over {maps.side:.0f} nm at the lift "
                        f"height, {fc.shift_n:+.3f} V (A) and {fc.shift_l:+.3f} V (B) down to contact: A "
                        f"{maps.a.min():.3f} to {maps.a.max():.3f} V, B {maps.b.min():.3f} to {maps.b.max():.3f} V "
                        f"(eq. 3.28-3.29)",))
    scale = max(config.preload, 50.0)
    cap = 0.5 * setup.full_scale * k_n.value          # half the detector's range
    loads = np.linspace(0.15, 1.0, setup.loads) * min(2.0 * scale, cap)
    flat = yield from _loops(tip, sites.flat, loads, setup)
    sign = _lateral_sign(sites.flat, config)
    half = (flat[:, 2] - flat[:, 1]) / (2.0 * sign)
    dw = fit.flat_loop_fit(flat[:, 0], half)
    yield Msg("event", (f"substrate loop: {len(loads)} loads of {loads[0]:.0f}-{loads[-1]:.0f} nm, half-width "
                        f"{dw.value:.4f} ± {dw.sigma:.4f} V per V of S_n",))
    tilt, down, up, slope_data = yield from _slope(tip, sites, loads, setup, fc.crosstalk)
    sf = fit.slope_fit(tilt, down, up, k, k_n)
    mu_ts = fit.friction_from_substrate(dw, sf.lateral_gain, k, k_n)
    yield Msg("event", (f"slope loops: tilt {tilt.value:.2f} ± {tilt.sigma:.2f} deg, dS_l/dS_n {down.value:.4f} "
                        f"(down) and {up.value:.4f} (up): k_l K_l / h = {sf.lateral_gain.value:.2f} ± "
                        f"{sf.lateral_gain.sigma:.2f} nN/V, mu = {sf.mu.value:.4f} on the slope (eq. 3.26-3.27); "
                        f"mu_ts = {mu_ts.value:.4f} ± {mu_ts.sigma:.4f} on the substrate",))
    edge_loads = np.linspace(0.2, 1.0, setup.edge_loads) * min(3.0 * scale, cap)
    order = np.concatenate([edge_loads, edge_loads[::-1]])
    edges = yield from _edge(tip, sites, order, setup)
    c2 = fit.edge_fit(edges[:, 0], edges[:, 1], edges[:, 2])
    yield Msg("event", (f"edge: {len(order)} passes of {edge_loads[0]:.0f}-{edge_loads[-1]:.0f} nm: C2 = "
                        f"{c2.value:.2f} ± {c2.sigma:.2f} nm/V (eq. 3.30-3.34)",))
    ratio = setup.tip_height / setup.length
    c1 = Value(k_n.value * ratio, k_n.sigma * ratio)
    yield Msg("event", (f"C1 = K_n h / l = {c1.value:.3f} ± {c1.sigma:.3f} nm/V (h = {setup.tip_height:g} nm, "
                        f"l = {setup.length:g} nm, seed 3.6.3)",))
    values = {"k": Value(k, 0.0), "K_n": k_n, "C1": c1, "C2": c2, "lateral_gain": sf.lateral_gain,
              "alpha": fc.crosstalk, "mu_ts": mu_ts, "mu_slope": sf.mu, "tilt": tilt}
    steps = {"force_curve": {**curve, "fit": fc}, "baselines": {**lifted, "maps": maps},
             "substrate_loop": {"rows": flat, "half": half, "fit": dw, "loads": loads},
             "slope_loops": {**slope_data, "fit": sf, "loads": loads},
             "edge": {"rows": edges, "fit": c2}}
    return Calibration(values, maps, {"tip_height": setup.tip_height, "length": setup.length}, steps)


__all__ = ["Calibration", "CalibrationFailed", "CalibrationSetup", "CalibrationSites", "calibrate"]
