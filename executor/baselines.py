"""The detector's free-air baselines A(i, j) and B(i, j) (seed eq. 3.28-3.29) over the scanner.

The substrate's reflection adds A to S_n and the piezo tube's bow adds B to S_l, both
varying over the scan (seed Fig. 3.13-3.14); eq. 3.28 removes them, with the normal-to-
lateral cross-talk α: ``S̄n = S_n − A(i, j)``, ``S̄l = S_l − B(i, j) − α S̄n``. The maps are
``n`` x ``n`` images in image order (``a[j, i]``: row ``j`` from the top, as
:func:`~nanoasm.world.cantilever.baseline_index`) over a square of the scanner frame, at
the height of a tip in contact (``nanoasm calibrate`` records them at the lift height and
brings them down by the approach of its force curve). A sample is looked up at its
scanner position by eq. 3.29; outside the square the nearest edge cell counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.param import ParamError
from nanoasm.world.cantilever import baseline_index

#: Most cells per side of a map (a TOML file holds n² numbers per map).
MAX_PIXELS = 128


@dataclass(frozen=True, eq=False)
class BaselineMaps:
    """A(i, j) and B(i, j) in volts over the square ``origin`` + [0, side]² (scanner nm)."""

    origin: tuple[float, float]
    side: float
    a: np.ndarray
    b: np.ndarray

    def __post_init__(self) -> None:
        if len(self.origin) != 2 or not all(math.isfinite(v) for v in self.origin):
            raise ParamError("origin", f"must be two finite numbers, got {self.origin!r}")
        if not (math.isfinite(self.side) and self.side > 0):
            raise ParamError("side", f"must be positive, got {self.side!r}")
        for name in ("a", "b"):
            m = np.asarray(getattr(self, name), float)
            if m.ndim != 2 or m.shape[0] != m.shape[1] or not 1 <= m.shape[0] <= MAX_PIXELS:
                raise ParamError(name.upper(), f"must be a square n x n map with 1 <= n <= {MAX_PIXELS}, "
                                               f"got shape {m.shape}")
            if not np.all(np.isfinite(m)):
                raise ParamError(name.upper(), "must hold finite volts only")
            object.__setattr__(self, name, m)
        if self.a.shape != self.b.shape:
            raise ParamError("B", f"must have the shape of A {self.a.shape}, got {self.b.shape}")
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))
        object.__setattr__(self, "side", float(self.side))

    @property
    def pixels(self) -> int:
        return int(self.a.shape[0])

    def at(self, xy) -> tuple[np.ndarray, np.ndarray]:
        """``(A, B)`` in volts at scanner positions ``xy`` ``(..., 2)`` nm (eq. 3.29)."""
        p = np.asarray(xy, float)
        half = 0.5 * self.side
        i, j = baseline_index(p[..., 0] - self.origin[0] - half, p[..., 1] - self.origin[1] - half,
                              self.side, self.pixels)
        return self.a[j, i], self.b[j, i]

    def compensate(self, s_n, s_l, xy, crosstalk: float) -> tuple[np.ndarray, np.ndarray]:
        """``(S̄n, S̄l)`` of eq. 3.28 for raw signals at scanner positions ``xy``."""
        a, b = self.at(xy)
        sn = np.asarray(s_n, float) - a
        return sn, np.asarray(s_l, float) - b - crosstalk * sn

    def to_table(self) -> dict:
        """The instrument file's ``[baseline]`` table."""
        return {"origin": list(self.origin), "side": self.side,
                "A": [[float(v) for v in row] for row in self.a],
                "B": [[float(v) for v in row] for row in self.b]}


__all__ = ["MAX_PIXELS", "BaselineMaps"]
