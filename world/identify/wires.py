"""Flexible strands (DNA, soft nanowires): thin, level, open curves.

A piece that no straight capsule explains is still a wire when its outline is a thin
open curve: the longest path through its skeleton carries nearly all of the skeleton
(few side branches), it is several widths long, no wider than a tube of its height
would image, not flat-topped like a plateau, and level along its crest (a swept pile of
debris is not).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from skimage.morphology import skeletonize

from nanoasm.world.tipimage import Tip, ball_reach

#: A thin curve is a wire when its length is at least this many widths.
WIRE_ELONGATION = 5.0
#: A wire's mean width is at most this many times the width a tube of its height images at.
WIRE_WIDTH = 2.0
#: A wire's height along its crest varies (beyond noise) by at most this fraction.
WIRE_EVENNESS = 0.3
#: A wire's skeleton has at most this many pixels off its longest path, per path pixel.
WIRE_SPURS = 0.3
#: A wire has at most this fraction of its pixels above 90 % of its height.
FLAT_TOP = 0.5


def skeleton_path(mask: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The longest path through the skeleton of ``mask``.

    Returns
    -------
    length : float
        Length of the longest geodesic path along the skeleton, in pixels.
    spurs : float
        Skeleton pixels off that path (side branches, noise spurs).
    path : (k, 2) int array
        Its pixels (row, col) from one end to the other.
    """
    sk = skeletonize(mask)
    rows, cols = np.nonzero(sk)
    k = rows.size
    if k < 2:
        return float(k), 0.0, np.column_stack([rows, cols])
    index = -np.ones(mask.shape, dtype=int)
    index[rows, cols] = np.arange(k)
    src, dst, w = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r2, c2 = rows + dr, cols + dc
        ok = (r2 >= 0) & (r2 < mask.shape[0]) & (c2 >= 0) & (c2 < mask.shape[1])
        j = np.full(k, -1)
        j[ok] = index[r2[ok], c2[ok]]
        hit = j >= 0
        src.append(np.nonzero(hit)[0])
        dst.append(j[hit])
        w.append(np.full(np.count_nonzero(hit), math.hypot(dr, dc)))
    graph = csr_matrix((np.concatenate(w), (np.concatenate(src), np.concatenate(dst))), shape=(k, k))
    d0 = dijkstra(graph, directed=False, indices=0)
    far = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
    d1, pred = dijkstra(graph, directed=False, indices=far, return_predecessors=True)
    end = int(np.argmax(np.where(np.isfinite(d1), d1, -1)))
    path = [end]
    while path[-1] != far:
        path.append(int(pred[path[-1]]))
    length = float(d1[end])
    spurs = float(k - len(path))              # skeleton pixels off the path
    return length, spurs, np.column_stack([rows[path], cols[path]])


def strand_length(z: np.ndarray, piece: np.ndarray, peak: float, pixel_size: float, cut: float,
                  sigma: float, tip: Tip) -> float | None:
    """Length (nm) of ``piece`` read as a flexible strand, or None if it is not one.

    ``z`` are the levelled heights of the piece's window, ``peak`` its top (nm); the
    length is the skeleton's longest path plus the strand's diameter (its ends).
    """
    length_px, spurs, path = skeleton_path(piece)
    if length_px <= 0 or spurs > WIRE_SPURS * length_px:
        return None
    width_px = np.count_nonzero(piece) / length_px
    if length_px < WIRE_ELONGATION * width_px:
        return None
    tube = 2 * float(ball_reach(peak / 2, cut, tip))
    if width_px * pixel_size > WIRE_WIDTH * tube + 2 * pixel_size:
        return None
    if np.count_nonzero(z[piece] > 0.9 * peak) > FLAT_TOP * np.count_nonzero(piece):
        return None
    crest = z[path[:, 0], path[:, 1]]
    if math.sqrt(max(float(crest.var()) - sigma ** 2, 0.0)) > WIRE_EVENNESS * float(crest.mean()):
        return None
    return max(length_px * pixel_size + peak, peak)
