"""Random valid scenes: counts and size ranges in, a non-overlapping scene out.

Objects are placed one by one by rejection sampling: a candidate is kept when its
footprint keeps at least ``gap`` nm from every footprint placed so far (found through a
uniform grid, so thousands of objects cost little) and from every obstacle. The lever's
constants are drawn about the seed's (:func:`draw_lever`, ±``lever_spread``), so a dry-run
of a generated scene tests the calibration and compensation chain, not one lever.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.schema import Point

from .params import CantileverParams, DriftParams, NoiseParams, WorldParams
from .scene import Obstacle, Scene, scene_from_dict

#: Candidates tried per object before giving up.
ATTEMPTS = 400
#: The lever's constants drawn about nominal (:func:`draw_lever`), each its own factor.
LEVER_KEYS = ("k", "K_n", "C1", "C2", "lateral_gain", "alpha")
#: Relative half-width of the uniform spread of the lever's constants about nominal.
LEVER_SPREAD = 0.2


def draw_lever(seed: int, spread: float = LEVER_SPREAD) -> CantileverParams:
    """The seed's lever (:class:`CantileverParams` defaults) with ``k``, ``K_n``, ``C1``,
    ``C2``, ``lateral_gain`` and ``alpha`` each scaled by a factor uniform in
    [1 - spread, 1 + spread], from a generator of its own (``[seed, 19]``), to 4
    significant digits; ``spread = 0`` is the nominal lever."""
    nominal = CantileverParams()
    if spread == 0:
        return nominal
    f = np.random.default_rng([seed, 19]).uniform(1.0 - spread, 1.0 + spread, len(LEVER_KEYS))
    return replace(nominal, **{k: float(f"{getattr(nominal, k) * x:.4g}") for k, x in zip(LEVER_KEYS, f)})


@dataclass(frozen=True)
class SceneSpec:
    """What to generate. Ranges are ``(low, high)`` in nm; ``gap`` is the least clearance."""

    area: Point = (10000.0, 10000.0)
    particles: int = 20
    rods: int = 0
    obstacles: int = 0
    particle_diameter: Point = (60.0, 120.0)
    rod_length: Point = (500.0, 1300.0)
    rod_diameter: Point = (60.0, 100.0)
    obstacle_size: Point = (300.0, 1500.0)
    obstacle_height: Point = (20.0, 60.0)
    gap: float = 50.0
    drift: DriftParams | None = None
    noise: NoiseParams | None = None
    lever_spread: float = LEVER_SPREAD

    def check(self) -> None:
        """Raise InputError (naming the CLI option) for an impossible request."""
        def bad(option: str, problem: str):
            raise InputError(None, option, problem)

        if not all(math.isfinite(v) and v > 0 for v in self.area):
            bad("--area", "width and height must be positive")
        for option, n in (("--particles", self.particles), ("--rods", self.rods),
                          ("--obstacles", self.obstacles)):
            if n < 0:
                bad(option, f"must not be negative, got {n}")
        for option, (lo, hi) in (("--particle-diameter", self.particle_diameter),
                                 ("--rod-length", self.rod_length),
                                 ("--rod-diameter", self.rod_diameter),
                                 ("--obstacle-size", self.obstacle_size),
                                 ("--obstacle-height", self.obstacle_height)):
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                bad(option, f"needs 0 < MIN <= MAX, got {lo:g} {hi:g}")
        if self.rods and self.rod_length[1] < self.rod_diameter[0]:
            bad("--rod-length", "the longest rod is shorter than the thinnest rod's diameter")
        if not (math.isfinite(self.gap) and self.gap >= 0):
            bad("--gap", f"must not be negative, got {self.gap:g}")
        if not (math.isfinite(self.lever_spread) and 0 <= self.lever_spread <= 0.5):
            bad("--lever-spread", f"must lie in [0, 0.5], got {self.lever_spread:g}")


class _Grid:
    """Uniform grid over placed footprint cores for neighbour queries."""

    def __init__(self, cell: float):
        self.cell = cell
        self.cells: dict[tuple[int, int], list[int]] = {}
        self.geoms: list[shapely.Geometry] = []
        self.radii: list[float] = []

    def _keys(self, bounds):
        x0, y0, x1, y1 = bounds
        c = self.cell
        for i in range(int(x0 // c), int(x1 // c) + 1):
            for j in range(int(y0 // c), int(y1 // c) + 1):
                yield i, j

    def clear(self, body: Body, gap: float) -> bool:
        geom, r = body.geometry(), body.radius
        x0, y0, x1, y1 = body.bounds()
        reach = gap + r
        seen: set[int] = set()
        for key in self._keys((x0 - reach, y0 - reach, x1 + reach, y1 + reach)):
            for k in self.cells.get(key, ()):
                if k in seen:
                    continue
                seen.add(k)
                if shapely.distance(geom, self.geoms[k]) < r + self.radii[k] + gap:
                    return False
        return True

    def add(self, body: Body) -> None:
        k = len(self.geoms)
        self.geoms.append(body.geometry())
        self.radii.append(body.radius)
        for key in self._keys(body.bounds()):
            self.cells.setdefault(key, []).append(k)


def _obstacle(spec: SceneSpec, rng: np.random.Generator) -> Obstacle:
    w, h = rng.uniform(*spec.obstacle_size, size=2)
    w, h = min(w, 0.9 * spec.area[0]), min(h, 0.9 * spec.area[1])
    x = rng.uniform(0, spec.area[0] - w)
    y = rng.uniform(0, spec.area[1] - h)
    poly = ((x, y), (x + w, y), (x + w, y + h), (x, y + h))
    height = float(rng.uniform(*spec.obstacle_height))
    return Obstacle(tuple((round(px, 3), round(py, 3)) for px, py in poly), round(height, 3))


def _body(kind: str, i: int, spec: SceneSpec, rng: np.random.Generator) -> Body:
    if kind == "particle":
        d = round(float(rng.uniform(*spec.particle_diameter)), 3)
        half = d / 2
        at = (rng.uniform(half, spec.area[0] - half), rng.uniform(half, spec.area[1] - half))
        return Body(f"o{i}", "particle", (round(at[0], 3), round(at[1], 3)), d)
    d = round(float(rng.uniform(*spec.rod_diameter)), 3)
    length = round(float(rng.uniform(max(spec.rod_length[0], d), max(spec.rod_length[1], d))), 3)
    angle = round(float(rng.uniform(0.0, 180.0)), 3)
    at = (round(float(rng.uniform(0, spec.area[0])), 3), round(float(rng.uniform(0, spec.area[1])), 3))
    return Body(f"o{i}", "rod", at, d, angle, length)


def random_scene(spec: SceneSpec, seed: int) -> Scene:
    """A valid scene with the requested counts, reproducible from ``seed``.

    Raises
    ------
    InputError
        When the request is impossible or the objects do not fit without overlap.
    """
    spec.check()
    rng = np.random.default_rng(seed)
    obstacles: list[Obstacle] = []
    for _ in range(spec.obstacles):
        for _attempt in range(ATTEMPTS):
            ob = _obstacle(spec, rng)
            g = ob.geometry()
            if all(shapely.distance(g, o.geometry()) >= spec.gap for o in obstacles):
                obstacles.append(ob)
                break
        else:
            raise InputError(None, "--obstacles", f"only {len(obstacles)} of {spec.obstacles} obstacles "
                             "fit without overlap; use a larger --area or fewer/smaller obstacles")
    obstacle_union = shapely.union_all([o.geometry() for o in obstacles]) if obstacles else None
    biggest = max(spec.particle_diameter[1], spec.rod_length[1] if spec.rods else 0.0)
    grid = _Grid(max(biggest + spec.gap, 1.0))
    objects: list[Body] = []
    area = spec.area
    for kind, count, option in (("rod", spec.rods, "--rods"), ("particle", spec.particles, "--particles")):
        placed = 0
        for _ in range(count):
            for _attempt in range(ATTEMPTS):
                body = _body(kind, len(objects) + 1, spec, rng)
                x0, y0, x1, y1 = body.bounds()
                if x0 < 0 or y0 < 0 or x1 > area[0] or y1 > area[1]:
                    continue
                if obstacle_union is not None and \
                        shapely.distance(body.geometry(), obstacle_union) < body.radius + spec.gap:
                    continue
                if grid.clear(body, spec.gap):
                    grid.add(body)
                    objects.append(body)
                    placed += 1
                    break
            else:
                raise InputError(None, option, f"only {placed} of {count} {kind}s fit without overlap "
                                 f"in {area[0]:g} x {area[1]:g} nm; use a larger --area, fewer objects or a "
                                 "smaller --gap")
    params = WorldParams(cantilever=draw_lever(seed, spec.lever_spread),
                         **{k: v for k, v in (("drift", spec.drift), ("noise", spec.noise)) if v is not None})
    scene = Scene(area, tuple(objects), tuple(obstacles), params, seed)
    return scene_from_dict(scene.to_dict(), "generated scene")
