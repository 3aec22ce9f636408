"""Grains: the connected regions above the cut plane, split into single objects.

The seed identifies objects with an adjustable cut plane: whatever rises above it is an
object or an obstacle. Here a grain is an 8-connected region above the cut. Objects
closer than twice the tip broadening image as one grain, so each grain is split by a
watershed from its clearly separate peaks; the recorded height is the maximum of the
objects' images, so the watershed lines fall where one image overtakes the other.
"""

from __future__ import annotations

import numpy as np
import shapely
from scipy import ndimage
from skimage.measure import find_contours
from skimage.morphology import h_maxima
from skimage.segmentation import watershed

from .levelling import COPY_BAND

EIGHT = ndimage.generate_binary_structure(2, 2)
#: Adjacent pieces whose saddle reaches this fraction of the lower peak are one piece.
FUSE = 0.6


def label_grains(height: np.ndarray, cut: float, min_pixels: int = 1,
                 valid: np.ndarray | None = None, min_height: float | None = None
                 ) -> tuple[np.ndarray, int]:
    """Label the 8-connected regions of ``height > cut`` with at least ``min_pixels`` pixels
    (and a top of at least ``min_height``, if given).

    A region within a single row is a scan-line artefact (a streak), not an object:
    the tip images anything real over at least two lines; it is dropped.

    Returns
    -------
    labels : (ny, nx) int array
        0 for background, 1..n for grains in raster order (bottom row first).
    n : int
    """
    above = height > cut
    if valid is not None:
        above &= valid
    labels, n = ndimage.label(above, EIGHT)
    if n == 0:
        return labels, 0
    sizes = np.bincount(labels.ravel())
    keep = sizes >= max(min_pixels, 1)
    keep[0] = False
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is not None and box[0].stop - box[0].start < 2:
            keep[k] = False
    if min_height is not None:
        keep[1:] &= _tops(height, labels, n) >= min_height
    remap = np.zeros(n + 1, dtype=labels.dtype)
    remap[keep] = np.arange(1, np.count_nonzero(keep) + 1)
    for r in range(0, labels.shape[0], COPY_BAND):    # remap[labels] in place, a band at a time: no second image
        labels[r:r + COPY_BAND] = remap[labels[r:r + COPY_BAND]]
    return labels, int(np.count_nonzero(keep))


def _tops(height: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Each label's highest pixel, labels 1..n (every one labels a pixel): what
    ``ndimage.maximum(height, labels, 1..n)`` gives, from the labelled pixels alone (it
    sorted every pixel of the scan: 4 s of a 4000 x 4000 pixel scan's identification)."""
    inside = labels > 0
    tops = np.full(n, -np.inf, dtype=np.result_type(height.dtype, np.float64))
    np.maximum.at(tops, labels[inside] - 1, height[inside])
    return tops


def split_grain(height: np.ndarray, mask: np.ndarray, prominence: float) -> tuple[np.ndarray, np.ndarray]:
    """Split one grain (``mask`` within the window ``height``) at its separate peaks.

    Peaks are the regional maxima of the lightly smoothed heights that stand at least
    ``prominence`` nm above every path to a higher peak; each pixel of the grain goes to
    the peak its steepest ascent reaches (watershed); pieces joined by a high saddle
    are merged again (:func:`fuse_pieces`).

    Returns
    -------
    pieces : int array like ``mask``
        0 outside the grain, 1..n inside.
    peaks : (n + 1,) int array
        Number of separate peaks in each piece (index 0 unused): more than one marks
        humps fused into one piece, an aggregate or a pile.
    """
    smooth = ndimage.gaussian_filter(np.where(mask, height, 0.0), 1.0)
    smooth = np.where(mask, smooth, smooth[mask].min() if mask.any() else 0.0)
    peaks = h_maxima(smooth, prominence) & mask
    markers, n = ndimage.label(peaks, EIGHT)
    if n <= 1:
        return mask.astype(int), np.array([0, 1])
    pieces = watershed(-smooth, markers, mask=mask, connectivity=2)
    return fuse_pieces(pieces, smooth, n)


def fuse_pieces(pieces: np.ndarray, height: np.ndarray, n: int,
                fuse: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Merge adjacent pieces whose saddle is at least ``fuse`` times the lower peak.

    Separate objects image with a low saddle between them (bodies with a gap of half
    their diameter: about a quarter of the height); humps of one pile or aggregate with
    a high one. Pairs merge from the highest saddle down (a merge tree).

    Returns
    -------
    pieces : int array, relabelled 1..m
    peaks : (m + 1,) int array
        How many of the ``n`` pieces each new piece holds.
    """
    fuse = FUSE if fuse is None else fuse
    peaks = np.asarray(ndimage.maximum(height, pieces, np.arange(1, n + 1)), dtype=float)
    saddles: dict[tuple[int, int], float] = {}
    for da, db in (((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
                   ((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                   ((slice(1, None), slice(1, None)), (slice(None, -1), slice(None, -1))),
                   ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None)))):
        a, b = pieces[da], pieces[db]
        edge = (a != b) & (a > 0) & (b > 0)
        if not edge.any():
            continue
        lo = np.minimum(a[edge], b[edge]), np.maximum(a[edge], b[edge])
        passes = np.minimum(height[da][edge], height[db][edge])
        for i, j, v in zip(lo[0].tolist(), lo[1].tolist(), passes.tolist()):
            if v > saddles.get((i, j), -np.inf):
                saddles[(i, j)] = v
    parent = list(range(n + 1))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    top = np.concatenate([[0.0], peaks])
    for (i, j), v in sorted(saddles.items(), key=lambda kv: -kv[1]):
        ri, rj = find(i), find(j)
        if ri != rj and v >= fuse * min(top[ri], top[rj]):
            parent[rj] = ri
            top[ri] = max(top[ri], top[rj])
    roots = np.array([find(i) for i in range(n + 1)])
    _, relabel = np.unique(roots, return_inverse=True)
    return relabel[pieces], np.bincount(relabel[1:], minlength=int(relabel.max()) + 1)


def mask_polygon(mask: np.ndarray, origin: tuple[float, float], pixel_size: float,
                 tolerance: float | None = None) -> shapely.Polygon:
    """Outline of a pixel mask (holes filled) as a valid polygon in nm.

    ``origin`` is the position of the lower-left corner of ``mask[0, 0]``. The outline
    follows the half-pixel contour of the mask, simplified to ``tolerance`` nm (half a
    pixel by default); for several separate parts the largest is returned.
    """
    filled = ndimage.binary_fill_holes(mask)
    padded = np.pad(filled, 1).astype(float)
    best = None
    for c in find_contours(padded, 0.5):
        if len(c) < 4:
            continue
        rows, cols = c[:, 0] - 1, c[:, 1] - 1
        pts = np.column_stack([origin[0] + (cols + 0.5) * pixel_size,
                               origin[1] + (rows + 0.5) * pixel_size])
        poly = shapely.make_valid(shapely.Polygon(pts))
        for part in getattr(poly, "geoms", [poly]):
            if isinstance(part, shapely.Polygon) and (best is None or part.area > best.area):
                best = part
    if best is None:
        # A single pixel or a thin line: its square(s) outline it.
        iy, ix = np.nonzero(filled)
        x0, y0 = origin[0] + ix.min() * pixel_size, origin[1] + iy.min() * pixel_size
        x1, y1 = origin[0] + (ix.max() + 1) * pixel_size, origin[1] + (iy.max() + 1) * pixel_size
        return shapely.box(x0, y0, x1, y1)
    tol = 0.5 * pixel_size if tolerance is None else tolerance
    simple = shapely.make_valid(best.simplify(tol, preserve_topology=True))
    parts = [p for p in getattr(simple, "geoms", [simple]) if isinstance(p, shapely.Polygon)]
    out = max(parts, key=lambda p: p.area) if parts else best
    return shapely.Polygon(out.exterior.coords)


def touches_border(mask: np.ndarray, rows: slice, cols: slice, shape: tuple[int, int]) -> bool:
    """Whether ``mask`` (a window at ``rows``, ``cols`` of an image of ``shape``) reaches its border."""
    ny, nx = shape
    if rows.start == 0 and mask[0].any():
        return True
    if rows.stop == ny and mask[-1].any():
        return True
    if cols.start == 0 and mask[:, 0].any():
        return True
    return bool(cols.stop == nx and mask[:, -1].any())
