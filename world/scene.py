"""Scene v1 (``nanoasm.scene/1``): the truth of a simulated world.

Objects (particles and rods), fixed obstacles, and the world's physical parameters
(``[drift]``, ``[noise]`` and the further tables of :mod:`nanoasm.world.params`, each
defaulting to the seed's values), loaded from TOML or JSON into frozen, validated
value types. Every rejection is an
:class:`~nanoasm.errors.InputError` naming the file, the key path and the problem.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import shapely

from nanoasm.bodies import (
    Body,
    body_from_table,
    check_placement,
    check_unique_ids,
    polygon_from_table,
    polygon_geometry,
)
from nanoasm.fileio import Document, read_document
from nanoasm.schema import Point, Table, check_format

from .limits import MAX_PIXELS
from .params import TABLES, DriftParams, NoiseParams, WorldParams

FORMAT = "nanoasm.scene/1"
KINDS = ("particle", "rod")


@dataclass(frozen=True)
class Obstacle:
    """A fixed feature (electrode, debris, trench) of ``height`` nm over a polygon."""

    polygon: tuple[Point, ...]
    height: float

    def geometry(self) -> shapely.Polygon:
        return polygon_geometry(self.polygon)

    def to_dict(self) -> dict:
        return {"polygon": [list(p) for p in self.polygon], "height": self.height}


@dataclass(frozen=True)
class Scene(Document):
    """A simulated sample. ``drift``/``noise`` are None when the file leaves them to the world."""

    area: Point
    objects: tuple[Body, ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    params: WorldParams = field(default_factory=WorldParams)
    seed: int | None = None

    @property
    def drift(self) -> DriftParams:
        return self.params.drift

    @property
    def noise(self) -> NoiseParams:
        return self.params.noise

    def to_dict(self) -> dict:
        d: dict = {"format": FORMAT, "area": list(self.area)}
        if self.seed is not None:
            d["seed"] = self.seed
        d["object"] = [o.to_dict() for o in self.objects]
        if self.obstacles:
            d["obstacle"] = [o.to_dict() for o in self.obstacles]
        d.update(self.params.to_tables())
        return d


    def summary(self) -> str:
        n_p = sum(o.kind == "particle" for o in self.objects)
        n_r = sum(o.kind == "rod" for o in self.objects)
        return (f"{self.area[0]:g} x {self.area[1]:g} nm, {n_p} particle(s), {n_r} rod(s), "
                f"{len(self.obstacles)} obstacle(s)")


def scene_from_dict(data: dict, source: str | None = None) -> Scene:
    """Validate a parsed scene document."""
    check_format(data, source, FORMAT)
    t = Table(data, source)
    t.check_keys(required={"format", "area"}, optional={"seed", "object", "obstacle", *TABLES})
    area = t.pair("area", names=("width", "height"), positive=True)
    seed = t.integer("seed", None, nonnegative=True)

    otables = t.tables("object")
    objects = [body_from_table(ot, f"o{i}", KINDS)[0] for i, ot in enumerate(otables, start=1)]
    check_unique_ids(otables, objects)

    btables = t.tables("obstacle")
    obstacles, polys = [], []
    for bt in btables:
        bt.check_keys(required={"polygon", "height"})
        pts, poly = polygon_from_table(bt)
        obstacles.append(Obstacle(pts, bt.number("height", positive=True)))
        polys.append(poly)

    params = WorldParams.from_document(t)
    xy = params.scanner.xy_range
    if area[0] > xy[0] or area[1] > xy[1]:      # the sample sits centred under the scanner
        t.fail("area", f"{area[0]:g} x {area[1]:g} nm exceeds the scanner's XY range {xy[0]:g} x "
                       f"{xy[1]:g} nm ([scanner] xy_range)")

    _check_roughness(t, params, area)
    check_placement("object", otables, objects, area, btables, polys)

    return Scene(area, tuple(objects), tuple(obstacles), params, seed)


def _check_roughness(t: Table, params: WorldParams, area: Point) -> None:
    """The simulated roughness is one grid node per correlation length over the area and a
    margin of 20 lengths: at most MAX_PIXELS nodes."""
    sim = params.sim
    if sim.roughness_rms == 0:
        return
    nodes = [math.ceil(side / sim.roughness_length) + 44 for side in area]
    if nodes[0] * nodes[1] > MAX_PIXELS:
        least = max(area) / (math.isqrt(MAX_PIXELS) - 44)
        t.fail("sim.roughness_length", f"must be at least {least:.3g} nm over a {area[0]:g} x {area[1]:g} nm "
                                       f"area, got {sim.roughness_length:g} (the roughness grid would have "
                                       f"{nodes[0]} x {nodes[1]} nodes, at most MAX_PIXELS {MAX_PIXELS})")


def load_scene(path: str | os.PathLike) -> Scene:
    """Load a scene from TOML or JSON (by suffix, else by content)."""
    return scene_from_dict(read_document(path), str(path))
