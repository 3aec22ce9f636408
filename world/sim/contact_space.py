"""Object-object contacts in the simulated world: a moved body shoves what it touches.

Footprints are the bodies' discs and capsules (:class:`nanoasm.bodies.Body`). When one
body (the *driver*, pushed by the tip) moves by a displacement, :meth:`ContactSpace.push`
moves it in sub-steps no longer than half the smallest radius, and after each sub-step
projects every overlapping pair apart along the normal between their closest core
points (position-based, Gauss-Seidel sweeps). The driver never yields; a body touched
earlier in a chain is moved less than one touched later, so chains propagate forward.
Bodies translate only: particles by the seed's model (ch. 4.2), rods shoved by another
body as a simplification (no rotation from contacts).

Candidates come from a uniform grid updated as bodies move, so the cost of a push
depends on the bodies near its path, not on how many idle bodies the sample holds.

Near other objects (gap below ``vdw.range``) every body that moved gets a random lateral
error (van der Waals and electrostatic forces, seed 3.6.1), drawn from ``rng`` and itself
resolved as a small push so that nothing interpenetrates.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from nanoasm.bodies import TOUCH_EPS, Body
from nanoasm.world.params import VdwParams

_GAP = 1e-7  # relative clearance left between separated footprints
_MAX_SWEEPS = 2000
_EQUAL_AFTER = 200  # sweeps after which chain order is dropped and pairs split the overlap


def _closest(p0, p1, q0, q1):
    """Closest points of segments p0-p1 and q0-q1 (points allowed): ``(cx, cy, dx, dy)``."""
    d1x, d1y = p1[0] - p0[0], p1[1] - p0[1]
    d2x, d2y = q1[0] - q0[0], q1[1] - q0[1]
    rx, ry = p0[0] - q0[0], p0[1] - q0[1]
    a, e, f = d1x * d1x + d1y * d1y, d2x * d2x + d2y * d2y, d2x * rx + d2y * ry
    eps = 1e-18
    if a <= eps and e <= eps:
        s = t = 0.0
    elif a <= eps:
        s, t = 0.0, min(max(f / e, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry
        if e <= eps:
            s, t = min(max(-c / a, 0.0), 1.0), 0.0
        else:
            b = d1x * d2x + d1y * d2y
            den = a * e - b * b
            s = min(max((b * f - c * e) / den, 0.0), 1.0) if den > eps * a * e else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                s, t = min(max(-c / a, 0.0), 1.0), 0.0
            elif t > 1.0:
                s, t = min(max((b - c) / a, 0.0), 1.0), 1.0
    return p0[0] + d1x * s, p0[1] + d1y * s, q0[0] + d2x * t, q0[1] + d2y * t


class ContactSpace:
    """Movable footprints with a uniform-grid index; :meth:`push` shoves and resolves.

    Parameters
    ----------
    bodies : sequence of Body
        Particles and rods (any elongated kind); positions change, shapes do not.
    cell : float, optional
        Grid cell size in nm (default: twice the largest diameter).
    """

    def __init__(self, bodies: Sequence[Body], cell: float | None = None):
        self._bodies = list(bodies)
        n = len(self._bodies)
        cores = [b.core() for b in self._bodies]
        self._a = np.array([c[0] for c in cores], float).reshape(n, 2)
        self._b = np.array([c[1] for c in cores], float).reshape(n, 2)
        self._r = np.array([b.radius for b in self._bodies], float)
        self._centre = np.array([b.at for b in self._bodies], float).reshape(n, 2)
        if cell is None:
            cell = 4 * float(self._r.max()) if n else 1.0
        if not (math.isfinite(cell) and cell > 0):
            raise ValueError(f"cell must be positive and finite, got {cell}")
        self.cell = float(cell)
        self.pair_tests = 0  # closest-point evaluations so far (a measure of cost)
        self._grid: dict[tuple[int, int], set[int]] = {}
        self._cells: list[tuple[int, int, int, int]] = [(0, 0, -1, -1)] * n
        for i in range(n):
            self._index(i)

    # -- state -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._bodies)

    @property
    def bodies(self) -> tuple[Body, ...]:
        return tuple(self._bodies)

    def centres(self) -> np.ndarray:
        """Current centres, ``(n, 2)`` nm (a copy)."""
        return self._centre.copy()

    # -- grid --------------------------------------------------------------------------------
    def _cell_range(self, i: int, margin: float = 0.0) -> tuple[int, int, int, int]:
        r = self._r[i] + margin
        lo = np.minimum(self._a[i], self._b[i]) - r
        hi = np.maximum(self._a[i], self._b[i]) + r
        c = self.cell
        return (math.floor(lo[0] / c), math.floor(lo[1] / c), math.floor(hi[0] / c), math.floor(hi[1] / c))

    def _index(self, i: int) -> None:
        new = self._cell_range(i)
        old = self._cells[i]
        if new == old:
            return
        for key in _cells(old):
            bucket = self._grid.get(key)
            if bucket is not None:
                bucket.discard(i)
                if not bucket:
                    del self._grid[key]
        for key in _cells(new):
            self._grid.setdefault(key, set()).add(i)
        self._cells[i] = new

    def units_near(self, lo, hi) -> np.ndarray | None:
        """Units whose grid cells meet the box ``lo``-``hi`` (a superset of those whose
        footprint's box does), sorted; None when the box spans more cells than there are
        units (a test of every unit is then cheaper)."""
        c = self.cell
        x0, y0 = math.floor(lo[0] / c), math.floor(lo[1] / c)
        x1, y1 = math.floor(hi[0] / c), math.floor(hi[1] / c)
        if (x1 - x0 + 1) * (y1 - y0 + 1) > len(self._bodies):
            return None
        found: set[int] = set()
        for key in _cells((x0, y0, x1, y1)):
            found |= self._grid.get(key, set())
        return np.array(sorted(found), dtype=np.int64)

    def _neighbours(self, i: int, margin: float = 0.0) -> list[int]:
        found: set[int] = set()
        for key in _cells(self._cell_range(i, margin)):
            found |= self._grid.get(key, set())
        found.discard(i)
        return sorted(found)

    # -- geometry ----------------------------------------------------------------------------
    def _move(self, i: int, dx: float, dy: float) -> None:
        d = (dx, dy)
        self._a[i] += d
        self._b[i] += d
        self._centre[i] += d
        self._index(i)

    def _separation(self, i: int, j: int, hint: tuple[float, float]):
        """``(gap, nx, ny)``: gap between footprints (negative when they overlap) and the
        unit normal from i to j."""
        self.pair_tests += 1
        cx, cy, dx, dy = _closest(self._a[i], self._b[i], self._a[j], self._b[j])
        vx, vy = dx - cx, dy - cy
        dist = math.hypot(vx, vy)
        reach = self._r[i] + self._r[j]
        if dist > 1e-9 * max(1.0, reach):
            return dist - reach, vx / dist, vy / dist
        # cores touch or cross: separate along the centre line, else along the motion
        for ux, uy in ((self._centre[j, 0] - self._centre[i, 0], self._centre[j, 1] - self._centre[i, 1]),
                       hint):
            norm = math.hypot(ux, uy)
            if norm > 1e-12:
                return -reach, ux / norm, uy / norm
        return -reach, 1.0, 0.0

    def _resolve(self, driver: int, hint: tuple[float, float], moved: set[int]) -> None:
        gen = {driver: 0}
        active = [driver]
        for sweep in range(_MAX_SWEEPS):
            changed = False
            for i in sorted(active, key=lambda k: (gen[k], k)):
                for j in self._neighbours(i):
                    gap, nx, ny = self._separation(i, j, hint)
                    reach = self._r[i] + self._r[j]
                    if gap >= -TOUCH_EPS * max(1.0, reach):
                        continue
                    if j not in gen:
                        gen[j] = gen[i] + 1
                        active.append(j)
                    wi, wj = self._weights(i, j, gen, driver, sweep)
                    depth = -gap + _GAP * max(1.0, reach)
                    if wi:
                        self._move(i, -wi * depth * nx, -wi * depth * ny)
                        moved.add(i)
                    if wj:
                        self._move(j, wj * depth * nx, wj * depth * ny)
                        moved.add(j)
                    changed = True
            if not changed:
                return
        raise RuntimeError(f"contacts around body {driver} did not settle in {_MAX_SWEEPS} sweeps")

    @staticmethod
    def _weights(i: int, j: int, gen: dict[int, int], driver: int, sweep: int) -> tuple[float, float]:
        if i == driver:
            return 0.0, 1.0
        if j == driver:
            return 1.0, 0.0
        if sweep < _EQUAL_AFTER and gen[i] != gen[j]:
            return (0.0, 1.0) if gen[i] < gen[j] else (1.0, 0.0)
        return 0.5, 0.5

    # -- pushing -----------------------------------------------------------------------------
    def _drive(self, index: int, dx: float, dy: float, moved: set[int]) -> None:
        length = math.hypot(dx, dy)
        if length == 0.0:
            return
        n = max(1, math.ceil(length / (0.5 * float(self._r.min()))))
        hint = (dx / length, dy / length)
        for _ in range(n):
            self._move(index, dx / n, dy / n)
            moved.add(index)
            self._resolve(index, hint, moved)

    def push(self, index: int, displacement: tuple[float, float], *,
             rng: np.random.Generator | None = None, vdw: VdwParams | None = None) -> list[int]:
        """Move body ``index`` by ``displacement`` (nm), shoving whatever it touches.

        With ``vdw`` and ``rng``, each body that moved and ends within ``vdw.range`` of
        another gets a Gaussian lateral error of ``vdw.amplitude`` nm per axis. Returns
        the sorted indices of the bodies that moved; :attr:`bodies` has their new positions.
        """
        if not 0 <= index < len(self._bodies):
            raise IndexError(f"body index {index} out of range 0..{len(self._bodies) - 1}")
        dx, dy = (float(v) for v in displacement)
        if not (math.isfinite(dx) and math.isfinite(dy)):
            raise ValueError(f"displacement must be finite, got {displacement}")
        if vdw is not None and rng is None:
            raise ValueError("a van der Waals error needs an rng")
        moved: set[int] = set()
        self._drive(index, dx, dy, moved)
        if vdw is not None and vdw.amplitude > 0 and moved:
            for m in sorted(moved):
                if self._near_other(m, vdw.range):
                    ex, ey = rng.normal(0.0, vdw.amplitude, size=2)
                    self._drive(m, float(ex), float(ey), moved)
        for m in moved:
            self._bodies[m] = dataclasses.replace(self._bodies[m], at=tuple(self._centre[m].tolist()))
        return sorted(moved)

    def _near_other(self, i: int, within: float) -> bool:
        return any(self._separation(i, j, (1.0, 0.0))[0] < within for j in self._neighbours(i, within))


def _cells(rng: tuple[int, int, int, int]):
    x0, y0, x1, y1 = rng
    return ((cx, cy) for cx in range(x0, x1 + 1) for cy in range(y0, y1 + 1))


def resolve_contacts(bodies: Sequence[Body], index: int, displacement: tuple[float, float], *,
                     rng: np.random.Generator | None = None, vdw: VdwParams | None = None) -> list[Body]:
    """One push on a fresh :class:`ContactSpace`; returns all bodies at their new positions.

    Building the index costs O(n); a world that pushes repeatedly keeps one ContactSpace.
    """
    space = ContactSpace(bodies)
    space.push(index, displacement, rng=rng, vdw=vdw)
    return list(space.bodies)
