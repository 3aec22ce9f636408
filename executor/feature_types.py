"""Fixed features as value types: where a straight obstacle edge crosses half its
height (:class:`EdgeSite`), and an edge's or a corner's sites (:class:`Feature`), with
their JSON forms for checkpoints. :mod:`~nanoasm.executor.fixed_features` finds them in
the full scan. Lengths in nm; ``row`` is an image row index (row 0 at the bottom,
scanned first).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.param import number

from .scan_lines import point

KINDS = ("edge", "corner")


@dataclass(frozen=True)
class EdgeSite:
    """Where the half-height crossing of a straight obstacle edge lies in the full scan.

    Attributes
    ----------
    point : (x, y)
        The crossing (nm, the image's frame = the layout frame).
    normal : (nx, ny)
        Unit normal of the edge, from the obstacle (high side) to the substrate.
    height : float
        Step height (nm) measured there.
    std : float
        1-sigma of the point's coordinate along ``normal`` (nm).
    row : float
        Mean image row index of the pixels the crossing was read from (the caller turns
        it into the time the row was scanned, to take out the drift during the scan).
    room : float
        How far (nm) a line may land from the site along the edge and still cross the
        same straight side: to the side's nearer end, or for a corner site to where the
        corner's rounding begins. A line is only worth scanning when the position
        along the edge is known better than that.
    """

    point: tuple[float, float]
    normal: tuple[float, float]
    height: float
    std: float
    row: float
    room: float = math.inf

    def __post_init__(self) -> None:
        p = point("point", self.point)
        n = point("normal", self.normal)
        if abs(math.hypot(*n) - 1.0) > 1e-6:
            raise ValueError(f"normal must be a unit vector, got {self.normal!r}")
        object.__setattr__(self, "point", (float(p[0]), float(p[1])))
        object.__setattr__(self, "normal", (float(n[0]), float(n[1])))
        object.__setattr__(self, "height", number("height", self.height, positive=True))
        object.__setattr__(self, "std", number("std", self.std, positive=True))
        object.__setattr__(self, "row", number("row", self.row))
        if not (self.room >= 0):
            raise ValueError(f"room must be non-negative, got {self.room!r}")
        object.__setattr__(self, "room", float(self.room))


@dataclass(frozen=True)
class Feature:
    """A fixed feature: ``"edge"`` (two sites on one straight edge: one coordinate,
    checked twice) or ``"corner"`` (one site on each edge of a sharp corner: both)."""

    id: str
    kind: str
    obstacle: int
    sites: tuple[EdgeSite, ...]

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if not isinstance(self.id, str) or not self.id:
            raise ValueError(f"id must be a non-empty string, got {self.id!r}")
        if not self.sites or not all(isinstance(s, EdgeSite) for s in self.sites):
            raise ValueError("sites must be a non-empty tuple of EdgeSite")
        object.__setattr__(self, "sites", tuple(self.sites))

    def normals(self) -> np.ndarray:
        """The sites' normals, (m, 2) array."""
        return np.array([s.normal for s in self.sites])


def feature_to_dict(f: Feature) -> dict:
    return {"id": f.id, "kind": f.kind, "obstacle": f.obstacle,
            "sites": [{"point": list(s.point), "normal": list(s.normal), "height": s.height, "std": s.std,
                       "row": s.row, "room": s.room if math.isfinite(s.room) else None} for s in f.sites]}


def feature_from_dict(d: dict) -> Feature:
    sites = tuple(EdgeSite(tuple(float(v) for v in s["point"]), tuple(float(v) for v in s["normal"]),
                           float(s["height"]), float(s["std"]), float(s["row"]),
                           math.inf if s.get("room") is None else float(s["room"])) for s in d["sites"])
    return Feature(str(d["id"]), str(d["kind"]), int(d["obstacle"]), sites)
