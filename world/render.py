"""Simulated AFM topography: full scans and single scan lines of a sample.

The true surface is the substrate (smooth correlated roughness about z = 0) with, on
it, spheres for particles, cylinders with hemispherical ends for rods (both resting
on z = 0, so their top is at their diameter) and flat plateaus for obstacles. The
recorded height is the grey dilation of that surface by the tip
(:mod:`nanoasm.world.tipimage`), computed exactly: the dilation of a maximum of
surfaces is the maximum of their dilations, and each body's dilation has a closed
form, drawn only in its bounding box. The roughness is smooth on the scale of the tip
(its correlation length is several tip radii), so the tip follows it.

On top come per-sample height noise, occasional scan-line offsets, and drift: the
scan acquires rows bottom to top, one every ``line_time`` seconds, and while row ``i``
is recorded the tip at nominal position ``p`` touches the sample at
``p + drift(t_i)`` (``drift`` gives the scanner-versus-sample offset in nm).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.instrument import HeightImage
from nanoasm.schema import Point

from .roughness import Roughness, make_roughness
from .tipimage import Tip, ball_image, ball_reach, plateau_image, segment_distance, tip_reach

#: Pixels of a full scan whose substrate is evaluated at once (memory for its coordinates).
_BAND_PIXELS = 1 << 20
#: Drift model: times (n,) in s -> scanner-versus-sample offsets (n, 2) in nm.
DriftFn = Callable[[np.ndarray], np.ndarray]


def _obstacle(obs) -> tuple[shapely.Polygon, float]:
    if isinstance(obs, tuple) and len(obs) == 2:
        poly, height = obs
    else:
        poly, height = obs.polygon, obs.height
    if not isinstance(poly, shapely.Polygon):
        pts = list(poly)
        if len(pts) > 3 and tuple(pts[0]) == tuple(pts[-1]):
            pts = pts[:-1]
        poly = shapely.Polygon(pts)
    if not (poly.is_valid and poly.area > 0):
        raise ValueError("obstacles: every polygon must be valid with a positive area")
    if not (math.isfinite(height) and height > 0):
        raise ValueError(f"obstacles: height must be positive, got {height}")
    shapely.prepare(poly)
    return poly, float(height)


@dataclass(frozen=True, eq=False)
class Surface:
    """A sample: bodies resting on a rough substrate, and flat obstacles, over ``area``.

    Replace ``bodies`` (``dataclasses.replace``) to image the same sample after pushes.
    """

    area: Point
    bodies: tuple[Body, ...] = ()
    obstacles: tuple[tuple[shapely.Polygon, float], ...] = ()
    roughness: Roughness | None = None


def make_surface(bodies: Sequence[Body], obstacles: Sequence, area: Point, *,
                 roughness_rms: float = 0.2, roughness_length: float = 50.0,
                 rng: np.random.Generator) -> Surface:
    """Build a :class:`Surface`.

    Parameters
    ----------
    bodies : sequence of Body
        Particles and rods (kind ``"wire"`` is drawn as a rod).
    obstacles : sequence
        Each with ``.polygon`` (points or shapely Polygon) and ``.height``, or a
        ``(polygon, height)`` pair.
    area : (w, h)
        Sample area in nm, lower-left corner at (0, 0).
    roughness_rms, roughness_length : float
        Substrate roughness in nm and its correlation length in nm (0 rms: flat).
    rng : numpy.random.Generator
    """
    if len(area) != 2 or not all(math.isfinite(v) and v > 0 for v in area):
        raise ValueError(f"area must be two positive numbers, got {area}")
    if not (math.isfinite(roughness_rms) and roughness_rms >= 0):
        raise ValueError(f"roughness_rms must be non-negative and finite, got {roughness_rms}")
    rough = make_roughness(area, roughness_rms, roughness_length, rng) if roughness_rms > 0 else None
    return Surface((float(area[0]), float(area[1])), tuple(bodies),
                   tuple(_obstacle(o) for o in obstacles), rough)


# ---------------------------------------------------------------- per-feature images

def _body_reach(body: Body, floor: float, tip: Tip) -> float:
    return float(ball_reach(body.radius, floor, tip))


def _body_image(body: Body, x: np.ndarray, y: np.ndarray, tip: Tip) -> np.ndarray:
    p, q = body.core()
    return ball_image(segment_distance(x, y, p, q), body.radius, tip)


def _obstacle_image(poly: shapely.Polygon, height: float, x: np.ndarray, y: np.ndarray,
                    tip: Tip) -> np.ndarray:
    x, y = np.broadcast_arrays(x, y)
    d = shapely.distance(poly, shapely.points(x.ravel(), y.ravel())).reshape(x.shape)
    return plateau_image(d, height, tip)


def _features(surface: Surface, floor: float, tip: Tip):
    """(bounding box grown by the image's reach down to ``floor``, image function) per feature."""
    out = []
    for b in surface.bodies:
        r = _body_reach(b, floor, tip)
        x0, y0, x1, y1 = b.bounds()
        out.append(((x0 - r + b.radius, y0 - r + b.radius, x1 + r - b.radius, y1 + r - b.radius),
                    lambda x, y, b=b: _body_image(b, x, y, tip)))
    for poly, h in surface.obstacles:
        r = float(tip_reach(h - floor, tip))
        x0, y0, x1, y1 = poly.bounds
        out.append(((x0 - r, y0 - r, x1 + r, y1 + r),
                    lambda x, y, poly=poly, h=h: _obstacle_image(poly, h, x, y, tip)))
    return out


def _floor(surface: Surface) -> float:
    """A height below every substrate height: features are drawn down to it."""
    return -(surface.roughness.bound if surface.roughness is not None else 0.0) - 1e-6


# ---------------------------------------------------------------- scans

def _check_common(noise_rms: float, rng) -> None:
    if not (math.isfinite(noise_rms) and noise_rms >= 0):
        raise ValueError(f"noise_rms must be non-negative and finite, got {noise_rms}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator")


def _drift_offsets(drift: DriftFn | None, ny: int, t0: float, line_time: float) -> np.ndarray:
    if drift is None:
        return np.zeros((ny, 2))
    t = t0 + line_time * np.arange(ny)
    off = np.asarray(drift(t), dtype=float)
    if off.shape != (ny, 2) or not np.all(np.isfinite(off)):
        raise ValueError(f"drift must return finite offsets of shape ({ny}, 2), got {off.shape}")
    return off


def render_scan(surface: Surface, pixel_size: float, *, tip: Tip = Tip(),
                window: tuple[float, float, float, float] | None = None,
                noise_rms: float = 0.3, line_offset_prob: float = 0.0,
                line_offset_rms: float = 0.0, drift: DriftFn | None = None,
                line_time: float = 1.0, t0: float = 0.0,
                rng: np.random.Generator) -> HeightImage:
    """A simulated full scan of ``surface``.

    Parameters
    ----------
    surface : Surface
    pixel_size : float
        Pixel pitch in nm; the image has ``round(w / pixel_size)`` columns.
    tip : Tip
    window : (x0, y0, w, h), optional
        Scanned region in nm; the whole ``surface.area`` by default.
    noise_rms : float
        Gaussian height noise per sample, nm.
    line_offset_prob, line_offset_rms : float
        Each row is offset as a whole, with this probability, by a Gaussian of this rms (nm).
    drift : callable, optional
        ``drift(t)`` for times ``(n,)`` returns ``(n, 2)`` scanner-versus-sample offsets
        in nm; row ``i`` is acquired at ``t0 + i * line_time`` and shows the sample
        around ``nominal + drift(t_i)``.
    rng : numpy.random.Generator
        Source of the noise and line offsets.

    Returns
    -------
    HeightImage
        Heights in nm, row 0 at the bottom, ``origin`` at the window's lower-left corner.
    """
    if not (math.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    _check_common(noise_rms, rng)
    if not 0 <= line_offset_prob <= 1:
        raise ValueError(f"line_offset_prob must be in [0, 1], got {line_offset_prob}")
    if not (math.isfinite(line_offset_rms) and line_offset_rms >= 0):
        raise ValueError(f"line_offset_rms must be non-negative, got {line_offset_rms}")
    if not (math.isfinite(line_time) and line_time > 0):
        raise ValueError(f"line_time must be positive, got {line_time}")
    wx, wy, ww, wh = window if window is not None else (0.0, 0.0, *surface.area)
    nx, ny = int(round(ww / pixel_size)), int(round(wh / pixel_size))
    if nx < 2 or ny < 2:
        raise ValueError(f"pixel_size {pixel_size} gives fewer than 2x2 pixels for the window")
    off = _drift_offsets(drift, ny, t0, line_time)
    xs = wx + (np.arange(nx) + 0.5) * pixel_size
    ys = wy + (np.arange(ny) + 0.5) * pixel_size + off[:, 1]
    dx = off[:, 0]

    z = np.zeros((ny, nx))
    if surface.roughness is not None:       # in bands of rows: each point alone, bounded memory
        band = max(1, _BAND_PIXELS // nx)
        for r in range(0, ny, band):
            rows = slice(r, r + band)
            z[rows] = surface.roughness(xs[None, :] + dx[rows, None], np.broadcast_to(ys[rows, None], z[rows].shape))
    for (x0, y0, x1, y1), image in _features(surface, _floor(surface), tip):
        rows = np.nonzero((ys >= y0) & (ys <= y1))[0]
        if rows.size == 0:
            continue
        lo = math.floor((x0 - dx[rows].max() - wx) / pixel_size - 0.5)
        hi = math.ceil((x1 - dx[rows].min() - wx) / pixel_size - 0.5)
        lo, hi = max(lo, 0), min(hi, nx - 1)
        if lo > hi:
            continue
        cols = np.arange(lo, hi + 1)
        block = image(xs[None, cols] + dx[rows, None], ys[rows, None])
        sub = np.ix_(rows, cols)
        z[sub] = np.maximum(z[sub], block)

    if line_offset_prob > 0 and line_offset_rms > 0:
        hit = rng.random(ny) < line_offset_prob
        z += (hit * rng.normal(0.0, line_offset_rms, ny))[:, None]
    if noise_rms > 0:
        z += rng.normal(0.0, noise_rms, z.shape)
    return HeightImage(z, float(pixel_size), (float(wx), float(wy)), "simulated",
                       {"tip_radius": tip.radius, "tip_half_angle": tip.half_angle})


def surface_heights(surface: Surface, x: np.ndarray, y: np.ndarray, *, tip: Tip = Tip()) -> np.ndarray:
    """Noise-free recorded heights at arbitrary points ``(x, y)`` (1-D arrays of one length)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"x and y must be 1-D arrays of one length, got {x.shape} and {y.shape}")
    z = surface.roughness(x, y) if surface.roughness is not None else np.zeros(x.shape)
    for (x0, y0, x1, y1), image in _features(surface, _floor(surface), tip):
        near = np.nonzero((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))[0]
        if near.size:
            z[near] = np.maximum(z[near], image(x[near], y[near]))
    return z


def surface_near(surface: Surface, cores: tuple[np.ndarray, np.ndarray, np.ndarray], lo, hi, *,
                 tip: Tip = Tip(), margin: float = 1.0) -> Surface:
    """``surface`` with only the bodies whose image can reach the box ``lo``-``hi`` (nm):
    what a scan line there sees, found in one array operation instead of a loop over every
    body. ``cores``: the bodies' core end points ``(n, 2)``, ``(n, 2)`` and radii ``(n,)``
    (a :class:`~nanoasm.world.sim.contacts.SimContacts`'s, in the order of
    ``surface.bodies``). The boxes are those :func:`surface_heights` tests, grown by
    ``margin`` nm for rounding, so its heights in the box are exactly the whole surface's."""
    a, b, r = cores
    if r.size == 0:
        return surface
    reach = ball_reach(r, _floor(surface), tip) + margin     # bounds() is the core grown by r
    near = np.all((np.minimum(a, b) - reach[:, None] <= np.asarray(hi, float))
                  & (np.maximum(a, b) + reach[:, None] >= np.asarray(lo, float)), axis=1)
    bodies = surface.bodies
    return Surface(surface.area, tuple(bodies[i] for i in np.flatnonzero(near)), surface.obstacles,
                   surface.roughness)


def render_line(surface: Surface, a: Point, b: Point, n: int, *, tip: Tip = Tip(),
                noise_rms: float = 0.3, rng: np.random.Generator) -> np.ndarray:
    """Heights along a scan line from ``a`` to ``b`` (nm, sample frame).

    Samples ``n`` equally spaced points ``a + (b - a) * k / (n - 1)``; the heights are
    the exact tip-surface contact heights of :func:`render_scan` (same physics, no
    pixel grid) plus Gaussian noise of ``noise_rms``. Drift is the caller's: shift
    ``a`` and ``b`` by the offset at the time of the line.

    Returns
    -------
    (n,) float array
    """
    if not (isinstance(n, (int, np.integer)) and n >= 2):
        raise ValueError(f"n must be an integer of at least 2, got {n!r}")
    if not all(math.isfinite(v) for v in (*a, *b)):
        raise ValueError("a and b must be finite points")
    _check_common(noise_rms, rng)
    s = np.linspace(0.0, 1.0, int(n))
    x = a[0] + (b[0] - a[0]) * s
    y = a[1] + (b[1] - a[1]) * s
    z = surface_heights(surface, x, y, tip=tip)
    if noise_rms > 0:
        z = z + rng.normal(0.0, noise_rms, z.shape)
    return z
