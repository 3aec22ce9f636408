"""Identification: a height image in, the environment (objects and obstacles) out.

The pipeline follows the seed's cut plane (section 3.2): level the image
(:mod:`.levelling`), keep what rises above a cut plane ``cut`` nm over the
substrate, drop regions smaller than ``min_area``, split each region at its separate
peaks (:mod:`.grains`), and classify every piece by fitting the exact tip
image of a ball or a straight capsule (:mod:`.pieces`,
:mod:`.resolve`). Pieces of one region that are not clean objects, and
objects that touch each other (aggregates), become obstacles: the outline of their
pixels above the cut (holes filled), with their height.

Coordinates are nm in the environment's frame, whose (0, 0) is the image's lower-left
corner (the corner of pixel (0, 0)) and whose area is the image's extent: a file's
``origin`` (a scanner offset) moves nothing out of that area; the environment records
it as its own ``origin``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NoReturn

import numpy as np
import shapely
from scipy import ndimage

from nanoasm.errors import InputError
from nanoasm.instrument import HeightImage
from nanoasm.param import check_number
from nanoasm.world.environment import Environment, EnvObject, EnvObstacle
from nanoasm.world.limits import MAX_HEIGHT, MAX_PIXEL_SIZE, MAX_TIP_RADIUS, MIN_PIXEL_SIZE
from nanoasm.world.tipimage import Tip

from .grains import EIGHT, label_grains, mask_polygon, touches_border
from .levelling import COPY_BAND, Levelled, default_cut, level
from .pieces import Context, Piece, tolerance
from .resolve import Grain, measure_grain, resolve_grain

#: With the automatic cut, a region must rise this many sigmas above the cut.
AUTO_MARGIN = 3.0
#: Default least area of a region, in pixels, when ``min_area`` is not given.
MIN_PIXELS = 4
#: Edge objects keep this fraction of their confidence.
EDGE_CONFIDENCE = 0.5


@dataclass(frozen=True, eq=False)
class Analysis:
    """Everything identification computed: the environment, the levelled image, the cut
    used (nm), the grain labels (0 background), per grain its classified pieces, and
    the fit tolerance (relative excess residual) used for the image."""

    environment: Environment
    levelled: Levelled
    cut: float
    grains: np.ndarray
    pieces: tuple[tuple[Piece, ...], ...]
    tolerance: float


def _check_option(src: str, key: str, value, **limits) -> None:
    """An option out of ``limits`` raises InputError naming the image and ``key``; None passes."""
    if value is None:
        return

    def fail(problem: str) -> NoReturn:
        raise InputError(src, key, problem)

    check_number(value, fail, **limits)


def identify(image: HeightImage, *, cut: float | None = None, min_area: float | None = None,
             min_height: float | None = None, pixel_size: float | None = None, tip_radius: float = 10.0,
             tip_half_angle: float = 20.0, rod_limit: float = 25.0, plane_order: int = 1,
             line_order: int = 0) -> Environment:
    """Find the particles, rods, wires and obstacles of a height image.

    Parameters
    ----------
    image : HeightImage
        Heights in nm, row 0 at the bottom.
    cut : float, optional
        Cut plane in nm above the levelled substrate; by default the substrate's
        histogram mode plus 5 robust sigmas, at least 0.5 nm.
    min_area : float, optional
        Least area (nm²) of a region above the cut; 4 pixels by default.
    min_height : float, optional
        Least top height (nm) of a region. By default none with an explicit ``cut``;
        with the automatic cut, 3 sigmas above it (substrate texture stays out).
    pixel_size : float, optional
        Overrides the image's pixel size (nm); either must lie within
        :data:`~nanoasm.world.limits.MIN_PIXEL_SIZE` to ``MAX_PIXEL_SIZE``.
    tip_radius, tip_half_angle : float
        The tip (nm, degrees): first guess of the tip radius, which is refined per
        object, and the fixed cone half angle.
    rod_limit : float
        Largest aspect ratio L/d of a rod; straighter, more slender objects are wires.
    plane_order, line_order : int
        Levelling: degree of the background polynomial and of the per-row alignment.

    Returns
    -------
    Environment
        ``area`` is the image's extent and (0, 0) its lower-left corner, whatever the
        image's ``origin``: every object lies in the area. That corner's position in the
        file's own coordinates (an absolute-coordinate scan's offset) is the
        environment's ``origin``. Ids are ``o1, o2, ...``.

    Raises
    ------
    InputError
        For an option out of range, an image with no finite height or with heights
        beyond :data:`~nanoasm.world.limits.MAX_HEIGHT`.
    """
    corner = (float(image.origin[0]), float(image.origin[1]))
    if pixel_size is not None and image.pixel_size > 0:     # the file's coordinates scale with it too
        corner = (corner[0] * pixel_size / image.pixel_size, corner[1] * pixel_size / image.pixel_size)
    image = replace(image, origin=(0.0, 0.0))
    env = analyse(image, cut=cut, min_area=min_area, min_height=min_height, pixel_size=pixel_size,
                  tip_radius=tip_radius, tip_half_angle=tip_half_angle, rod_limit=rod_limit,
                  plane_order=plane_order, line_order=line_order).environment
    return replace(env, origin=corner)


def analyse(image: HeightImage, *, cut: float | None = None, min_area: float | None = None,
            min_height: float | None = None, pixel_size: float | None = None, tip_radius: float = 10.0,
            tip_half_angle: float = 20.0, rod_limit: float = 25.0, plane_order: int = 1,
            line_order: int = 0) -> Analysis:
    """:func:`identify`, returning the intermediate results too."""
    src = image.source or "image"
    _check_option(src, "cut", cut, positive=True)
    _check_option(src, "min_area", min_area, nonnegative=True)
    _check_option(src, "min_height", min_height, nonnegative=True)
    _check_option(src, "pixel_size", pixel_size, lo=MIN_PIXEL_SIZE, hi=MAX_PIXEL_SIZE)
    _check_option(src, "tip_radius", tip_radius, positive=True, hi=MAX_TIP_RADIUS)
    if not (isinstance(tip_half_angle, (int, float)) and 0 < tip_half_angle < 90):
        raise InputError(src, "tip_half_angle", f"must be in (0, 90) degrees, got {tip_half_angle!r}")
    _check_option(src, "rod_limit", rod_limit, lo=1)
    if plane_order not in (0, 1, 2, 3) or line_order not in (0, 1, 2):
        raise InputError(src, "levelling", "plane_order must be 0-3 and line_order 0-2")
    if pixel_size is not None:
        image = replace(image, pixel_size=float(pixel_size))
    _check_option(src, "pixel_size", image.pixel_size, lo=MIN_PIXEL_SIZE, hi=MAX_PIXEL_SIZE)
    finite = np.isfinite(image.height)
    if not finite.any():
        raise InputError(src, None, "the image has no finite height")
    top = _top(image.height, finite)
    if top > MAX_HEIGHT:
        raise InputError(src, None, f"heights reach {top:.3g} nm; at most {MAX_HEIGHT:g} nm (1 mm) are "
                                    "identified (a wrong unit?)")

    lev = level(image.height, plane_order=plane_order, line_order=line_order)
    auto_cut = cut is None
    cut = default_cut(lev) if auto_cut else float(cut)
    ps = image.pixel_size
    min_pixels = MIN_PIXELS if min_area is None else max(1, math.ceil(min_area / ps ** 2 - 1e-9))
    if min_height is None and auto_cut:
        min_height = cut + AUTO_MARGIN * lev.sigma
    labels, n = label_grains(lev.height, cut, min_pixels, lev.valid, min_height=min_height)
    ctx = Context(ps, (float(image.origin[0]), float(image.origin[1])),
                  Tip(tip_radius, tip_half_angle), cut, lev.sigma, float(rod_limit))

    boxes = ndimage.find_objects(labels)
    grains = [measure_grain(lev.height, labels, lev.valid, g, box, ctx)
              for g, box in enumerate(boxes, start=1)]
    tol = tolerance([m.fit for gr in grains for m in gr.measured if m.fit is not None], ctx)
    objects: list[EnvObject] = []
    obstacles: list[EnvObstacle] = []
    resolved = []
    for gr in grains:
        pieces, masks = resolve_grain(gr, tol, ctx)
        _record(gr, pieces, masks, labels.shape, ctx, objects, obstacles)
        resolved.append(tuple(pieces))
    env = Environment(image.extent, tuple(objects), tuple(obstacles), image.source or None)
    return Analysis(env, lev, cut, labels, tuple(resolved), tol)


def _top(height: np.ndarray, finite: np.ndarray, band: int = COPY_BAND) -> float:
    """``float(np.max(np.abs(height[finite])))`` (some pixel is finite), a band of rows at a
    time: no image-sized copies (each costs a 4000 x 4000 pixel scan a third of a second)."""
    return max(float(np.max(np.abs(height[r:r + band][finite[r:r + band]]), initial=0.0))
               for r in range(0, height.shape[0], band))


def _record(gr: Grain, pieces: list[Piece], masks: list[np.ndarray], shape: tuple[int, int],
            ctx: Context, objects: list[EnvObject], obstacles: list[EnvObstacle]) -> None:
    """Append a grain's objects, and the outlines of its obstacle pieces, to the lists."""
    rest = np.zeros_like(gr.mask)
    for piece, pm in zip(pieces, masks):
        if piece.kind == "obstacle":
            rest |= pm
            continue
        edge = touches_border(pm, gr.rows, gr.cols, shape)
        conf = piece.confidence * (EDGE_CONFIDENCE if edge else 1.0)
        objects.append(EnvObject(
            f"o{len(objects) + 1}", piece.kind, (round(piece.centre[0], 3), round(piece.centre[1], 3)),
            round(piece.diameter, 3),
            None if piece.angle is None else round(piece.angle % 180.0, 3),
            None if piece.length is None else round(max(piece.length, piece.diameter), 3),
            round(min(max(conf, 0.0), 1.0), 3), edge))
    if not rest.any():
        return
    parts, n = ndimage.label(rest, EIGHT)
    origin = (ctx.origin[0] + gr.cols.start * ctx.pixel_size, ctx.origin[1] + gr.rows.start * ctx.pixel_size)
    for i in range(1, n + 1):
        part = parts == i
        poly = mask_polygon(part, origin, ctx.pixel_size)
        height = max(p.height for p, pm in zip(pieces, masks) if (pm & part).any())
        pts = tuple((round(x, 3), round(y, 3)) for x, y in poly.exterior.coords[:-1])
        if not shapely.Polygon(pts).is_valid:      # rounding pinched it: take the hull
            hull = shapely.Polygon(pts).convex_hull
            pts = tuple((round(x, 3), round(y, 3)) for x, y in hull.exterior.coords[:-1])
        obstacles.append(EnvObstacle(pts, round(height, 3), touches_border(part, gr.rows, gr.cols, shape)))
