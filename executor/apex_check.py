"""A particle slot seen in a small image when its check lines cannot tell.

A neighbour that touches the slot's particle, or one lying where a check line ends (an
object pushed astray and lost, which the belief cannot steer the lines around), hides
the edges the lines look for: the bump runs off the line, or two bumps merge. A small
raster image of the slot shows every body at once. A sphere of radius R imaged by a
spherical tip of radius r is a sphere of radius R + r about the same centre, so each
particle's image has one apex, straight above its centre and ``2R`` above the
substrate, however its neighbours crowd it; touching particles' images meet in a saddle
below both apexes.

Each apex is a local maximum of the levelled image; a quadratic surface fitted to the
pixels within :data:`CAP` of the image's radius of it locates the apex to a fraction
of a pixel. Its height is the particle's diameter, and its two curvatures are alike: a
rod's image is a ridge, curved across and flat along (their ratio near 0), so a rod
crossing the slot is not taken for a particle (:data:`ROUND`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.world.identify.levelling import fit_surface, robust_sigma

from .context import RunContext
from .edges import TALLER_ONLY, TOUCHING
from .engine import Msg

__all__ = ["CROWDED", "Apex", "apex_cov", "apex_pixel", "find_apices", "image_check"]

#: Why a line found nothing when a neighbour ran into it (the bump runs off the line's
#: end, two bumps merge, or only a taller one is on the line): where the lines of a
#: pattern say so, an image can tell.
CROWDED = ("object cut by the line end", TOUCHING, TALLER_ONLY)

#: Pixels per particle diameter of the image (at most :data:`LARGEST_PIXEL` nm, at
#: least :data:`SMALLEST_PIXEL`).
PER_DIAMETER = 10.0
LARGEST_PIXEL = 10.0
SMALLEST_PIXEL = 1.0
#: The cap fitted about an apex: pixels within this fraction of the radius of the
#: particle's image (its radius and the tip's, :data:`TIP_ALLOWANCE`).
CAP = 0.45
#: Fewest pixels a cap fit takes.
MIN_CAP_PIXELS = 9
#: Smallest ratio of the lesser to the greater curvature of a particle's apex.
ROUND = 0.4
#: Pixels within this fraction of the diameter of the lowest tenth are the substrate
#: the image is levelled on.
SUBSTRATE = 0.1
#: Largest reach, in diameters, an image is taken for: farther, the estimate does not
#: know where the particle is (the strategies that measure no drift: hundreds of nm),
#: several particles in the image could be it, and the image costs minutes.
MAX_REACH = 1.0
#: Tip radius (nm) the window allows for on each side.
TIP_ALLOWANCE = 12.0


@dataclass(frozen=True)
class Apex:
    """One apex found in an image: ``at`` (nm, the image's frame), its height above
    the substrate (nm), the ratio of its curvatures (1 for a sphere, near 0 along a
    ridge) and its 1-σ position precision (nm)."""

    at: tuple[float, float]
    height: float
    roundness: float
    std: float


def apex_pixel(diameter: float) -> float:
    """The pixel size (nm) of a slot's check image for particles of ``diameter`` nm."""
    return float(min(max(diameter / PER_DIAMETER, SMALLEST_PIXEL), LARGEST_PIXEL))


def _fit_cap(z: np.ndarray, i: int, j: int, radius_px: float, noise: float):
    """Quadratic fit z = c0 + c1 x + c2 y + c3 x² + c4 xy + c5 y² (pixels, about pixel
    (i, j)) over the pixels within ``radius_px``; returns (x, y, height, roundness, std)
    of its apex in pixels, or None where the fit has no maximum there."""
    r = math.ceil(radius_px)
    ii, jj = np.mgrid[max(i - r, 0):min(i + r + 1, z.shape[0]), max(j - r, 0):min(j + r + 1, z.shape[1])]
    dy, dx = (ii - i).ravel().astype(float), (jj - j).ravel().astype(float)
    keep = dx * dx + dy * dy <= radius_px * radius_px
    if np.count_nonzero(keep) < MIN_CAP_PIXELS:
        return None
    dx, dy = dx[keep], dy[keep]
    h = z[ii.ravel()[keep], jj.ravel()[keep]]
    a = np.column_stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy])
    c, *_ = np.linalg.lstsq(a, h, rcond=None)
    hess = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    curv = np.linalg.eigvalsh(hess)
    if not curv[1] < 0:
        return None                                  # no maximum: a saddle or a slope
    x0, y0 = np.linalg.solve(hess, -c[1:3])
    if math.hypot(x0, y0) > radius_px:
        return None                                  # the fit's apex is not in its cap
    top = float(c[0] + 0.5 * (c[1] * x0 + c[2] * y0))
    # the apex's precision: the noise through the fit's gradient terms, over the curvature
    cov = noise * noise * np.linalg.inv(a.T @ a)[1:3, 1:3]
    std = float(math.sqrt(max(np.trace(cov), 0.0) / 2.0) / abs(curv[1]))
    return float(x0), float(y0), top, float(curv[1] / curv[0]), std


def _levelled(z: np.ndarray, diameter: float) -> tuple[np.ndarray, float]:
    """``z`` less the plane through its substrate, and the substrate's noise (nm). A
    plane only: a slot's image is mostly particles, too few substrate pixels in a row to
    align rows by (a row offset would tilt an apex's cap)."""
    z = np.where(np.isfinite(z), z, np.nanmin(z) if np.isfinite(z).any() else 0.0)
    use = z <= np.percentile(z, 10) + SUBSTRATE * diameter
    for _ in range(3):
        if np.count_nonzero(use) < 3:
            break
        z = z - fit_surface(z, use, 1)
        use = np.abs(z) <= max(3.0 * robust_sigma(z[use]), 0.5)
    return z, max(robust_sigma(z[use]) if np.count_nonzero(use) >= 3 else 0.0, 0.05)


def find_apices(height: np.ndarray, pixel: float, diameter: float) -> tuple[list[Apex], float]:
    """The particle apexes of a raw image ``height`` (nm, row 0 at the bottom) of pixel
    size ``pixel`` nm, for particles of ``diameter`` nm: local maxima above half the
    diameter, each fitted (:func:`_fit_cap`). Positions are in nm from the image's
    lower-left corner. Returns the apexes and the substrate noise (nm)."""
    from skimage.feature import peak_local_max

    z, noise = _levelled(np.asarray(height, float), diameter)
    radius_px = max(CAP * (diameter / 2.0 + TIP_ALLOWANCE) / pixel, 1.5)
    peaks = peak_local_max(z, min_distance=max(1, round(0.25 * diameter / pixel)),
                           threshold_abs=0.5 * diameter, exclude_border=False)
    out = []
    for i, j in peaks:
        fit = _fit_cap(z, int(i), int(j), radius_px, noise)
        if fit is None:
            continue
        x0, y0, top, ratio, std = fit
        out.append(Apex(((j + 0.5 + x0) * pixel, (i + 0.5 + y0) * pixel), top, ratio,
                        max(std * pixel, 0.1 * pixel)))
    return out, noise


def apex_cov(ctx: RunContext, apex: Apex) -> np.ndarray:
    """Covariance (nm²) of an apex of the last :func:`image_check`: its fit's precision
    and what the image's lines' drift compensation may err by (``ctx.scan_comp``)."""
    return np.eye(2) * apex.std ** 2 + ctx.scan_comp


def image_check(ctx: RunContext, centre, diameter: float, reach: float, label: str):
    """Scan a small image about ``centre`` (layout frame) and find the particle apexes in
    it (plan stub). ``reach``: how far (nm) the particle may lie from ``centre``. The
    image is a drift-compensated raster of local-scan lines (:func:`.scan_images.raster`).

    Returns (apexes as (Apex, position in the layout frame, time)) sorted by distance
    from ``centre``, and the image's pixels per side), or None where ``reach`` exceeds
    :data:`MAX_REACH` diameters or the window does not fit in the scanner's range.
    """
    from .scan_images import raster            # scan_steps looks with these images too

    if reach > MAX_REACH * diameter:
        return None
    pixel = apex_pixel(diameter)
    half = diameter / 2.0 + reach + TIP_ALLOWANCE
    lo, hi = np.asarray(ctx.config.lower[:2], float), np.asarray(ctx.config.upper[:2], float)
    t0 = yield Msg("clock")
    middle = np.asarray(centre, float) + ctx.offset(t0)
    x0, y0 = np.maximum(middle - half, lo)
    x1, y1 = np.minimum(middle + half, hi)
    side = min(x1 - x0, y1 - y0)
    if side < diameter:
        return None
    pixels = max(8, min(math.ceil(side / pixel), math.floor(float(np.min(hi - lo)) / pixel)))
    side = pixels * pixel
    if x0 + side > hi[0] or y0 + side > hi[1]:
        x0, y0 = min(x0, hi[0] - side), min(y0, hi[1] - side)
    heights, corner, t = yield from raster(ctx, (x0, y0), pixels, pixel, f"check image of {label}")
    apices, _ = find_apices(heights, pixel, diameter)
    out = [(a, corner + np.asarray(a.at), t) for a in apices]
    out.sort(key=lambda item: math.dist(item[1], centre))
    return out, pixels
