"""Measuring and classifying one piece of a grain (one candidate object).

:func:`measure_piece` fits the exact tip image of a ball or a straight capsule
(:mod:`.shapefit`) to a piece's pixels; :func:`classify` then decides by
how well the fit explains them. "Well" is relative to the image: real particles are
not perfect spheres and real tips are not the model's, so the tolerance on the excess
residual is set from the median of all fits of the image (:func:`tolerance`), between
4 % and 20 % of the height (8 % for images of fewer than 8 pieces). The classes:

- ring (a hole in the region above the cut): obstacle;
- round, ball fits: particle;
- elongated, straight capsule fits: rod while σ = L/d is at most the rod limit, wire
  beyond it;
- elongated, thin, a single open curve that no straight capsule fits: wire (flexible,
  e.g. DNA);
- anything else (aggregates, plateaus, swept piles, irregular blobs): obstacle.

Diameters come from the fitted height, centres and rod axes from the fit, lengths from
the fitted core (the fit undoes the tip broadening with the exact cylinder-under-tip
geometry; the first guess uses the same geometry at the cut level).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from nanoasm.world.tipimage import Tip, ball_reach

from .shapefit import ShapeFit, capsule_model, fit_ball, fit_capsule
from .wires import strand_length

#: Least number of pixels (piece and rim) for a shape fit.
MIN_FIT_PIXELS = 10
#: Above this ratio of principal extents a piece is fitted as a capsule.
ELONGATED = 1.25
#: Below this aspect ratio L/d a fitted capsule is taken as a ball.
ROUND = 1.5
#: ... and also when its image at the cut is less than this many times longer than wide.
VISIBLE = 1.6
#: Bounds on the tolerated excess residual (fraction of the height) ...
TOLERANCE = (0.04, 0.20)
#: ... which is this many times the median excess of the image's fits ...
TOLERANCE_FACTOR = 2.0
#: ... when there are at least this many fits; else it is the default.
MIN_FITS = 8
TOLERANCE_DEFAULT = 0.08
#: A rod's crest varies (beyond noise) by at most this fraction of the fit tolerance.
RIDGE = 0.5
#: Confidence given to a wire found by its outline (no shape model fitted).
WIRE_CONFIDENCE = 0.6


@dataclass(frozen=True)
class Context:
    """What every piece of one image shares."""

    pixel_size: float
    origin: tuple[float, float]
    tip: Tip
    cut: float
    sigma: float
    rod_limit: float


@dataclass
class Piece:
    """One classified candidate; ``kind`` is particle, rod, wire or obstacle."""

    kind: str
    centre: tuple[float, float]
    diameter: float
    angle: float | None = None
    length: float | None = None
    confidence: float = 1.0
    height: float = 0.0
    fit: ShapeFit | None = None


def _coords(rows: np.ndarray, cols: np.ndarray, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
    return (ctx.origin[0] + (cols + 0.5) * ctx.pixel_size,
            ctx.origin[1] + (rows + 0.5) * ctx.pixel_size)


def _moments(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float, float, float]:
    """Weighted centroid, axis angle (degrees) and ratio of principal extents."""
    w = w / w.sum()
    cx, cy = float(w @ x), float(w @ y)
    dx, dy = x - cx, y - cy
    cov = np.array([[w @ (dx * dx), w @ (dx * dy)], [w @ (dx * dy), w @ (dy * dy)]])
    vals, vecs = np.linalg.eigh(cov)
    major = vecs[:, 1]
    ratio = math.sqrt(max(vals[1], 1e-12) / max(vals[0], 1e-12))
    return cx, cy, math.degrees(math.atan2(major[1], major[0])) % 180.0, ratio


def relative_excess(fit: ShapeFit, ctx: Context) -> float:
    """Residual of a fit beyond the substrate noise, as a fraction of its height."""
    excess = math.sqrt(max(fit.rms ** 2 - ctx.sigma ** 2, 0.0))
    return excess / max(fit.diameter, ctx.cut)


def tolerance(fits: list[ShapeFit], ctx: Context) -> float:
    """Tolerated relative excess for an image whose pieces were fitted by ``fits``."""
    values = [relative_excess(f, ctx) for f in fits if _fit_ok(f)]
    if len(values) < MIN_FITS:               # too few to learn from: a fixed middle value
        return TOLERANCE_DEFAULT
    return float(np.clip(TOLERANCE_FACTOR * np.median(values), *TOLERANCE))


def _elongated(fit: ShapeFit, ctx: Context) -> bool:
    """Whether a fitted capsule is a rod rather than a ball: aspect ratio L/d of at
    least ``ROUND``, an image at the cut visibly longer than wide (``VISIBLE``), and a
    core longer than the tip radius (a shorter one cannot be told from a tip artefact).
    """
    if fit.length < ROUND * fit.diameter:
        return False
    if 2 * fit.half_length < max(ctx.tip.radius, fit.tip_radius):
        return False
    tip = Tip(fit.tip_radius, ctx.tip.half_angle)
    width = float(ball_reach(fit.radius, ctx.cut, tip))     # half-width of the image at the cut
    return fit.half_length >= (VISIBLE - 1.0) * width


def _fit_ok(fit: ShapeFit) -> bool:
    return fit.ok and fit.radius > 0 and math.isfinite(fit.rms)


@dataclass
class Measured:
    """A fitted piece before classification: moments, top height, the fit (None for
    rings and pieces too small to fit), the wire reading of its shape (None if it is
    not a thin open curve) and, for a capsule, the unevenness of its ridge
    (:func:`ridge_unevenness`)."""

    centre: tuple[float, float]
    angle: float
    peak: float
    fit: ShapeFit | None
    wire: Piece | None
    ridge: float = 0.0


def measure_piece(z: np.ndarray, piece: np.ndarray, fit_pixels: np.ndarray,
                  offset: tuple[int, int], ctx: Context) -> Measured:
    """Fit one piece.

    Parameters
    ----------
    z : (h, w) float array
        Levelled heights of a window of the image.
    piece : (h, w) bool array
        The piece's pixels above the cut.
    fit_pixels : (h, w) bool array
        Pixels the shape fit uses (the piece and a rim of substrate around it).
    offset : (row, col)
        Position of the window's pixel (0, 0) in the image.
    """
    r, c = np.nonzero(piece)
    x, y = _coords(r + offset[0], c + offset[1], ctx)
    h = z[r, c]
    # The top, robust to single-pixel spikes when the piece is big enough for a median.
    peak = float(ndimage.median_filter(np.where(piece, z, 0.0), 3)[piece].max()) if h.size >= 9 \
        else float(h.max())
    cx, cy, angle, ratio = _moments(x, y, np.maximum(h - ctx.cut, 1e-6))
    holes = np.count_nonzero(ndimage.binary_fill_holes(piece)) - r.size
    fr, fc = np.nonzero(fit_pixels)
    if holes >= 2 or fr.size < MIN_FIT_PIXELS:
        return Measured((cx, cy), angle, peak, None, None)
    fx, fy = _coords(fr + offset[0], fc + offset[1], ctx)
    fit = _fit_shape(fx, fy, z[fr, fc], x, y, (cx, cy), angle, ratio, peak, piece, ctx)
    ridge = ridge_unevenness(x, y, h, fit, ctx) if fit.half_length > 0 else 0.0
    wire = None
    if not (_fit_ok(fit) and relative_excess(fit, ctx) <= TOLERANCE[0] and ridge <= RIDGE * TOLERANCE[0]):
        # Not an object whatever the image's tolerance: could it be a flexible strand?
        length = strand_length(z, piece, peak, ctx.pixel_size, ctx.cut, ctx.sigma, ctx.tip)
        if length is not None:
            wire = Piece("wire", (cx, cy), peak, angle, length, WIRE_CONFIDENCE, peak)
    return Measured((cx, cy), angle, peak, fit, wire, ridge)


def ridge_unevenness(x: np.ndarray, y: np.ndarray, h: np.ndarray, fit: ShapeFit,
                     ctx: Context) -> float:
    """Spread of the heights along a capsule's crest beyond the noise, over its height.

    A cylinder's crest is level; a swept pile or a row of particles that happens to
    fit a capsule is not. The spread is that of the fit's residuals at the pixels
    within 0.75 pixel of the core segment (0 when fewer than 5).
    """
    th = math.radians(fit.angle)
    u = (x - fit.centre[0]) * math.cos(th) + (y - fit.centre[1]) * math.sin(th)
    v = -(x - fit.centre[0]) * math.sin(th) + (y - fit.centre[1]) * math.cos(th)
    on = (np.abs(v) <= 0.75 * ctx.pixel_size) & (np.abs(u) <= fit.half_length)
    if np.count_nonzero(on) < 5:
        return 0.0
    p = np.array([*fit.centre, th, fit.half_length, fit.radius, fit.tip_radius])
    resid = h[on] - capsule_model(p, x[on], y[on], ctx.tip.half_angle)
    return math.sqrt(max(float(resid.var()) - ctx.sigma ** 2, 0.0)) / max(fit.diameter, ctx.cut)


def classify(m: Measured, tol: float, ctx: Context) -> Piece:
    """Particle, rod or wire when the fit explains the piece within ``tol`` (relative
    excess residual; a rod's crest also level within ``RIDGE * tol``); else a wire when
    it is a thin open curve; else an obstacle."""
    if m.fit is not None and _fit_ok(m.fit):
        e = relative_excess(m.fit, ctx)
        if e <= tol and m.ridge <= RIDGE * tol:
            return _object(m.fit, math.exp(-0.5 * (e / tol) ** 2), ctx)
    if m.wire is not None:
        return m.wire
    return Piece("obstacle", m.centre, m.peak, height=m.peak, fit=m.fit)


def _fit_shape(fx, fy, fz, x, y, centre, angle, ratio, peak, piece, ctx: Context) -> ShapeFit:
    """Capsule fit for an elongated piece (kept if the result is elongated), else ball fit."""
    a0 = max(peak / 2, ctx.cut)
    span = math.hypot(*piece.shape) * ctx.pixel_size
    if ratio >= ELONGATED:
        cos, sin = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        u = (x - centre[0]) * cos + (y - centre[1]) * sin
        mid = 0.5 * (u.max() + u.min())
        # Half extent along the axis minus the half width a cylinder of this height
        # images at the cut: the core's half length, tip broadening removed.
        half = 0.5 * (u.max() - u.min()) + 0.5 * ctx.pixel_size
        core = max(half - float(ball_reach(a0, ctx.cut, ctx.tip)), 0.0)
        fit = fit_capsule(fx, fy, fz, centre=(centre[0] + mid * cos, centre[1] + mid * sin),
                          angle=angle, half_length=core, radius=a0, tip=ctx.tip, reach=span)
        if _fit_ok(fit) and _elongated(fit, ctx):
            return fit
    return fit_ball(fx, fy, fz, centre=centre, radius=a0, tip=ctx.tip, reach=span)


def _object(fit: ShapeFit, quality: float, ctx: Context) -> Piece:
    if fit.half_length == 0.0:
        return Piece("particle", fit.centre, fit.diameter, confidence=quality,
                     height=fit.diameter, fit=fit)
    sigma = fit.length / fit.diameter
    conf = quality
    if sigma > ctx.rod_limit:
        kind = "wire"
    else:
        kind = "rod"
        if sigma >= 15.0:                    # the seed's uncertain band, 15 <= sigma <= 25
            conf *= 0.8
    if sigma < 2 * ROUND:                    # close to the particle/rod boundary
        conf *= 0.9
    return Piece(kind, fit.centre, fit.diameter, fit.angle, fit.length, conf,
                 fit.diameter, fit)
