"""Relocalisation windows: square windows of the full scan whose content is distinctive
in both directions (an electrode's corner, a cluster of particles that will not be
pushed).

A small new scan of such a window, registered on the same window of the full scan
(:func:`~nanoasm.executor.registration.register`), measures the drift in both
coordinates at once. :func:`choose_windows` scores the candidates by the structure
tensor of their slopes and returns the best apart as :class:`Window`. Lengths in nm;
images are :class:`~nanoasm.instrument.HeightImage` (row 0 at the bottom, ``origin`` the
lower-left corner of pixel (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage
from skimage.filters import window as taper

from nanoasm.instrument import HeightImage
from nanoasm.param import number

#: Windows more masked than this fraction are not candidates.
MAX_MASKED = 0.5


@dataclass(frozen=True)
class Window:
    """A square window ``region = (x0, y0, x1, y1)`` (nm, the image's frame) and its
    score: the smaller eigenvalue of the structure tensor (squared slopes, nm/nm) summed
    over it, weighted towards its centre (see :func:`choose_windows`)."""

    region: tuple[float, float, float, float]
    score: float

    def __post_init__(self) -> None:
        x0, y0, x1, y1 = (number("region", v) for v in self.region)
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"region must have x1 > x0 and y1 > y0, got {self.region!r}")
        object.__setattr__(self, "region", (x0, y0, x1, y1))
        object.__setattr__(self, "score", number("score", self.score, nonnegative=True))


#: Pixels of an image made at once when windows are summed: more are made in bands of rows.
BAND_PIXELS = 1 << 22


def choose_windows(image: HeightImage, size: float, *, avoid=None, count: int = 3,
                   min_separation: float | None = None, margin: float | None = None
                   ) -> tuple[Window, ...]:
    """Square windows of side ``size`` whose content is distinctive in both directions.

    Each candidate (a grid of positions an eighth of the side apart) is scored by the
    smaller eigenvalue of the structure tensor ``sum w (g - mean g)(g - mean g)^T`` of the
    slopes ``g`` (Gaussian derivatives, one pixel) over its unmasked pixels: a corner of
    an electrode or a cluster of particles has slopes in both directions, a straight edge
    in one only, bare substrate hardly any; a tilt does not count. The weight ``w`` is a
    radial Hann window: content near the centre counts most, as it stays in view of a
    new scan that the drift has moved by a good part of the side. Pixels within
    ``margin`` of ``avoid`` are masked; candidates more than :data:`MAX_MASKED` masked
    are skipped.

    Parameters
    ----------
    image : HeightImage
        The full scan.
    size : float
        Side of the windows (nm), at least 8 pixels and at most the image.
    avoid : shapely geometry, optional
        What must not be relied on (objects that will be pushed, slots), image frame.
    count : int
        Most windows returned.
    min_separation : float, optional
        Least distance between chosen windows' centres (nm); ``size`` by default.
    margin : float, optional
        How near ``avoid`` a pixel is masked (nm); ``max(2 px, 20 nm)`` by default (the
        tip broadens what is imaged).

    Returns
    -------
    tuple of Window
        Best first; fewer than ``count`` when the candidates run out.
    """
    if not isinstance(image, HeightImage):
        raise ValueError(f"image must be a HeightImage, got {type(image).__name__}")
    ps = image.pixel_size
    size = number("size", size, positive=True)
    k = int(round(size / ps))
    ny, nx = image.shape
    if not 8 <= k <= min(nx, ny):
        raise ValueError(f"size must span 8 to {min(nx, ny)} pixels, got {size:g} nm ({k} pixels)")
    count = number("count", count, integer=True, lo=1)
    sep = size if min_separation is None else number("min_separation", min_separation, nonnegative=True)
    margin = max(2 * ps, 20.0) if margin is None else number("margin", margin, nonnegative=True)
    valid = np.ones(image.shape, bool) if avoid is None else ~_near(image, avoid, margin)
    gx = ndimage.gaussian_filter(image.height, 1.0, order=(0, 1)) / ps
    gy = ndimage.gaussian_filter(image.height, 1.0, order=(1, 0)) / ps
    step = max(1, k // 8)
    weight = taper("hann", (k, k))                 # what survives a shift counts most
    def masked(a, b=None):      # rows r0:r1 of a (or a b) times valid, made band by band
        return lambda r0, r1: (a[r0:r1] if b is None else a[r0:r1] * b[r0:r1]) * valid[r0:r1]

    terms = (masked(valid), masked(gx), masked(gy), masked(gx, gx), masked(gy, gy), masked(gx, gy))
    sums = [_window_sums(f, image.shape, weight, step) for f in terms]
    n, sx, sy, sxx, syy, sxy = sums
    nn = np.maximum(n, 1e-9)
    a, c, b = sxx - sx * sx / nn, syy - sy * sy / nn, sxy - sx * sy / nn
    score = np.maximum(0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b), 0.0)
    unmasked = _window_sums(lambda r0, r1: valid[r0:r1].astype(float), image.shape, np.ones((k, k)), step)
    score[unmasked < (1 - MAX_MASKED) * k * k] = -1.0
    chosen: list[Window] = []
    for flat in np.argsort(score, axis=None)[::-1]:
        if len(chosen) == count or score.flat[flat] < 0:
            break
        i, j = np.unravel_index(flat, score.shape)
        x0, y0 = image.origin[0] + j * step * ps, image.origin[1] + i * step * ps
        centre = np.array([x0 + 0.5 * k * ps, y0 + 0.5 * k * ps])
        if all(math.dist(centre, _centre(w)) >= sep for w in chosen):
            chosen.append(Window((x0, y0, x0 + k * ps, y0 + k * ps), float(score.flat[flat])))
    return tuple(chosen)


def _centre(w: Window) -> tuple[float, float]:
    x0, y0, x1, y1 = w.region
    return 0.5 * (x0 + x1), 0.5 * (y0 + y1)


def _near(image: HeightImage, geometry, margin: float) -> np.ndarray:
    """Pixels whose centres lie within ``margin`` of ``geometry``: inside it grown by
    ``margin`` (with no margin, in it or on its boundary). Each part of the grown geometry
    is tested only on the pixels of its bounding box: a whole scan of 4000 x 4000 pixels
    against the 496 parts of ``scale1000``'s pushed areas took 8.2 s point by point, the
    same mask. (A point of the geometry lies inside its buffer: a margin leaves nothing
    for the boundary test to add.)"""
    if not isinstance(geometry, shapely.Geometry):
        raise ValueError(f"avoid must be a shapely geometry, got {type(geometry).__name__}")
    x, y = image.pixel_centres()
    # parts of a (multi)polygon share no interior point: inside the whole is inside one part
    grown, test = (geometry, shapely.intersects_xy) if margin <= 0 else (geometry.buffer(margin), shapely.contains_xy)
    out = np.zeros(image.shape, bool)
    for part in shapely.get_parts(grown):
        rows, cols = _box_pixels(x, y, part)
        out[rows, cols] |= test(part, x[cols][None, :], y[rows][:, None])
    return out


def _box_pixels(x: np.ndarray, y: np.ndarray, part) -> tuple[slice, slice]:
    """Rows and columns of the pixel centres (``x`` of the columns, ``y`` of the rows,
    both increasing) within ``part``'s bounding box."""
    x0, y0, x1, y1 = shapely.bounds(part)
    return (slice(int(np.searchsorted(y, y0, "left")), int(np.searchsorted(y, y1, "right"))),
            slice(int(np.searchsorted(x, x0, "left")), int(np.searchsorted(x, x1, "right"))))


def _window_sums(field, shape: tuple[int, int], weight: np.ndarray, step: int) -> np.ndarray:
    """Sums of an image times ``weight`` (k x k) over the windows whose lower-left pixel
    lies on a ``step`` grid; ``field(r0, r1)`` gives the image's rows ``r0:r1`` (of
    ``shape``). Only the grid's windows are summed: the image is cut into blocks of
    ``step`` x ``step`` pixels and the weight likewise (padded with zeros to whole
    blocks), every block's product with every block of the weight is one matrix product,
    and each window adds its blocks' products up. (A correlation of the whole image kept
    one window in ``step²``: on ``scale1000``'s 4000-pixel scan, seven such sums took 8.5
    s.) The image is made in bands of rows (:data:`BAND_PIXELS`), so memory stays
    bounded."""
    k = weight.shape[0]
    nb = -(-k // step)                              # blocks a side of the weight
    wpad = np.zeros((nb * step, nb * step))
    wpad[:k, :k] = weight
    # (pixel within a block, block of the weight) -> weight
    wb = wpad.reshape(nb, step, nb, step).transpose(1, 3, 0, 2).reshape(step * step, nb * nb)
    ni, nj = (shape[0] - k) // step + 1, (shape[1] - k) // step + 1      # windows on the grid
    cols = (nj + nb - 1) * step                     # image columns the windows reach, whole blocks
    band = max(1, BAND_PIXELS // max(shape[1], 1) // step)                # windows' rows a band
    out = np.empty((ni, nj))
    for i0 in range(0, ni, band):
        i1 = min(i0 + band, ni)
        r0, r1 = i0 * step, (i1 - 1 + nb) * step    # rows of whole blocks the band's windows reach
        f = np.zeros((r1 - r0, cols))
        got = np.asarray(field(r0, min(r1, shape[0])), float)[:, :cols]
        f[:got.shape[0], :got.shape[1]] = got
        bi, bj = (r1 - r0) // step, cols // step
        blocks = f.reshape(bi, step, bj, step).transpose(0, 2, 1, 3).reshape(bi * bj, step * step)
        g = (blocks @ wb).reshape(bi, bj, nb, nb)  # block (I, J) times weight block (u, v)
        acc = np.zeros((i1 - i0, nj))
        for u in range(nb):
            for v in range(nb):
                acc += g[u:u + i1 - i0, v:v + nj, u, v]
        out[i0:i1] = acc
    return out
