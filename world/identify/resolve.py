"""One grain from pixels to pieces: split, fit, and decide what the grain holds.

:func:`measure_grain` splits a grain at its separate peaks and fits every piece.
:func:`resolve_grain`, given the image's fit tolerance, classifies the pieces; humps
fused into one piece (a high saddle between separate peaks) and objects whose fitted
footprints touch each other are aggregates or piles, hence obstacles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage

from nanoasm.world.tipimage import ball_image

from .grains import EIGHT, split_grain
from .pieces import Context, Measured, Piece, classify, measure_piece

#: Pixels of substrate around a piece that its shape fit also uses.
RIM = 2
#: Objects whose footprints come closer than this fraction of the smaller diameter touch.
TOUCH = 0.02


@dataclass
class Grain:
    """A grain's window in the image (``rows``, ``cols``), its ``mask`` there, the
    pieces' masks and measurements, and how many separate peaks each piece holds."""

    rows: slice
    cols: slice
    mask: np.ndarray
    masks: list[np.ndarray]
    measured: list[Measured]
    peaks: list[int]


def prominence(peak: float, sigma: float, ctx: Context) -> float:
    """Least height of a peak over its saddle for a grain to be split there.

    Above noise (5 sigma) and 5 % of the height, and above the ripple that pixel
    sampling puts on a ridge: the drop of the body's image half a pixel diagonal off
    its crest.
    """
    ripple = peak - float(ball_image(ctx.pixel_size / math.sqrt(2), peak / 2, ctx.tip))
    return max(5 * sigma, 0.05 * peak, 1.5 * ripple)


def measure_grain(z: np.ndarray, labels: np.ndarray, valid: np.ndarray, g: int,
                  box: tuple[slice, slice], ctx: Context) -> Grain:
    """Split and fit grain ``g`` (bounding box ``box`` in ``labels``)."""
    grow = RIM + 1
    rows = slice(max(box[0].start - grow, 0), min(box[0].stop + grow, labels.shape[0]))
    cols = slice(max(box[1].start - grow, 0), min(box[1].stop + grow, labels.shape[1]))
    lab = labels[rows, cols]
    zw = z[rows, cols]
    grain = lab == g
    free = (lab == 0) & valid[rows, cols]
    offset = (rows.start, cols.start)

    def rim(mask: np.ndarray) -> np.ndarray:
        return mask | (ndimage.binary_dilation(mask, EIGHT, iterations=RIM) & free)

    ring = np.count_nonzero(ndimage.binary_fill_holes(grain)) - np.count_nonzero(grain) >= 2
    if ring:                                   # a ring is one obstacle: never split it
        masks, peaks = [grain], [1]
    else:
        split, counts = split_grain(zw, grain, prominence(float(zw[grain].max()), ctx.sigma, ctx))
        masks = [split == k for k in range(1, counts.size)]
        peaks = [int(c) for c in counts[1:]]
    measured = [measure_piece(zw, pm, rim(pm), offset, ctx) for pm in masks]
    return Grain(rows, cols, grain, masks, measured, peaks)


def resolve_grain(grain: Grain, tol: float, ctx: Context) -> tuple[list[Piece], list[np.ndarray]]:
    """The grain's classified pieces and their masks (window coordinates)."""
    pieces = [classify(m, tol, ctx) for m in grain.measured]
    for piece, peaks in zip(pieces, grain.peaks):
        if peaks > 1:
            piece.kind = "obstacle"
    _mark_aggregates(pieces)
    return pieces, grain.masks


def _core(p: Piece) -> shapely.Geometry:
    if p.angle is None or p.length is None:
        return shapely.Point(p.centre)
    h = max(p.length - p.diameter, 0.0) / 2
    c, s = math.cos(math.radians(p.angle)), math.sin(math.radians(p.angle))
    return shapely.LineString([(p.centre[0] - h * c, p.centre[1] - h * s),
                               (p.centre[0] + h * c, p.centre[1] + h * s)])


def _mark_aggregates(pieces: list[Piece]) -> None:
    """Objects of one grain whose footprints touch are an aggregate: make them obstacles."""
    bodies = [(i, p, _core(p)) for i, p in enumerate(pieces) if p.kind != "obstacle"]
    touching = set()
    for a in range(len(bodies)):
        for b in range(a + 1, len(bodies)):
            (i, pa, ga), (j, pb, gb) = bodies[a], bodies[b]
            gap = shapely.distance(ga, gb) - (pa.diameter + pb.diameter) / 2
            if gap < TOUCH * min(pa.diameter, pb.diameter):
                touching.update((i, j))
    for i in touching:
        pieces[i].kind = "obstacle"
