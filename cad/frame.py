"""Frames: the transform that registers a layout's own (CAD) frame onto a scan's.

A layout with alignment marks (``[[mark]]``) is drawn in its own frame, the chip's; the
scan has its own, whose (0, 0) is the scanned area's lower-left corner. Registration
(:mod:`nanoasm.planner.alignment`) finds the :class:`Similarity` that maps the first
onto the second::

    x_scan = scale * R(rotation) @ x_layout + translation

and :func:`map_layout` moves a layout's slots, keep-outs and marks into the scan's frame
with it, so that planning and the run work in the scan's frame as they do without
marks. Plans, reports and run logs carry the transform (``registration``: rotation in
degrees, counter-clockwise; translation in nm; scale; the fit's RMS residual in nm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from nanoasm.bodies import Body
from nanoasm.schema import Point, Table


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * R(rotation) x + translation`` (degrees, nm); ``residual`` is the RMS
    residual of the fit that found it (nm), None when it was not fitted."""

    rotation: float = 0.0
    translation: Point = (0.0, 0.0)
    scale: float = 1.0
    residual: float | None = None

    def __post_init__(self) -> None:
        values = (self.rotation, *self.translation, self.scale)
        if len(self.translation) != 2 or not all(math.isfinite(v) for v in values):
            raise ValueError("a registration needs a finite rotation, translation and scale")
        if not self.scale > 0:
            raise ValueError(f"registration scale must be positive, got {self.scale:g}")
        if self.residual is not None and not (math.isfinite(self.residual) and self.residual >= 0):
            raise ValueError("registration residual must be a non-negative number")

    @property
    def matrix(self) -> np.ndarray:
        """The linear part, ``scale * R(rotation)`` (2 x 2)."""
        c, s = math.cos(math.radians(self.rotation)), math.sin(math.radians(self.rotation))
        return self.scale * np.array([[c, -s], [s, c]])

    def apply(self, points) -> np.ndarray:
        """``(N, 2)`` points mapped; an ``(N, 2)`` array."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        return p @ self.matrix.T + np.asarray(self.translation, dtype=float)

    def point(self, p: Point) -> Point:
        x, y = self.apply([p])[0]
        return float(x), float(y)

    def polygon(self, points) -> tuple[Point, ...]:
        return tuple((float(x), float(y)) for x, y in self.apply(points))

    def body(self, b: Body) -> Body:
        """``b`` (any Body, an identified object too) moved, turned and scaled."""
        if not b.elongated:
            return replace(b, at=self.point(b.at), diameter=b.diameter * self.scale)
        return replace(b, at=self.point(b.at), diameter=b.diameter * self.scale,
                       angle=(b.angle + self.rotation) % 180.0, length=b.length * self.scale)

    def inverse(self) -> Similarity:
        """The transform back (its residual is this one's, in this one's target frame)."""
        back = Similarity(-self.rotation, (0.0, 0.0), 1.0 / self.scale)
        tx, ty = back.apply([self.translation])[0]
        return Similarity(-self.rotation, (-float(tx), -float(ty)), 1.0 / self.scale, self.residual)

    @property
    def identity(self) -> bool:
        return self.rotation == 0 and self.translation == (0.0, 0.0) and self.scale == 1

    def to_dict(self) -> dict:
        d: dict = {"rotation": self.rotation, "translation": list(self.translation), "scale": self.scale}
        if self.residual is not None:
            d["residual"] = self.residual
        return d

    def line(self) -> str:
        """The transform in words, for a summary line."""
        text = (f"rotation {self.rotation:.3f} deg, translation ({self.translation[0]:.1f}, "
                f"{self.translation[1]:.1f}) nm, scale {self.scale:.5g}")
        return text if self.residual is None else f"{text}, residual {self.residual:.1f} nm"


def similarity_from_table(t: Table) -> Similarity:
    """A ``registration`` table of a plan or report (its keys checked, errors located)."""
    t.check_keys(required={"rotation", "translation", "scale"}, optional={"residual"})
    residual = None if t.is_null("residual") else t.number("residual", None, nonnegative=True)
    return Similarity(t.number("rotation", lo=-180.0, hi=180.0), t.pair("translation"),
                      t.number("scale", positive=True), residual)


def rounded(s: Similarity) -> Similarity:
    """``s`` with its figures rounded for files (1e-6 degrees, 1e-3 nm, 1e-9 scale)."""
    return Similarity(round(s.rotation, 6), (round(s.translation[0], 3), round(s.translation[1], 3)),
                      round(s.scale, 9), None if s.residual is None else round(s.residual, 3))
