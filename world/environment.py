"""Environment v1 (``nanoasm.env/1``): the objects identified on a sample.

Written by ``nanoasm identify``, read by ``nanoasm plan``. Objects are particles, rods
or wires (rod-like but too slender to push as a rigid rod); anything else is an
obstacle polygon. Objects or obstacles cut by the image border carry ``edge = True``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from nanoasm.bodies import (MAX_COORDINATE, TOUCH_EPS, Body, body_from_table, check_at, check_unique_ids,
                            polygon_from_table)
from nanoasm.errors import InputError
from nanoasm.fileio import dumps_json, read_document, write_atomic
from nanoasm.instrument.protocol import MAX_SCANNER_RANGE
from nanoasm.schema import Point, Table, check_format

from .limits import MAX_HEIGHT

FORMAT = "nanoasm.env/1"
KINDS = ("particle", "rod", "wire")


def _check_confidence(object_id: str, confidence: float) -> None:
    if not 0.0 <= confidence <= 1.0:
        raise ValueError(f"{object_id}: confidence must be in [0, 1]")


@dataclass(frozen=True)
class EnvObject(Body):
    """An identified object: a :class:`Body` with a confidence in [0, 1] and an edge flag."""

    confidence: float = 1.0
    edge: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.kind not in KINDS:
            raise ValueError(f"{self.id}: kind must be one of {KINDS}")
        _check_confidence(self.id, self.confidence)

    def changed(self, *, at=None, confidence: float | None = None) -> EnvObject:
        """``dataclasses.replace`` with a new ``at`` or ``confidence``, those checked as
        :meth:`__post_init__` checks them and the rest taken as it is (a belief of a
        thousand objects is put in the planner's terms at every replan: 7.5 -> 1.4 µs an
        object)."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        if at is not None:
            check_at(self.id, at)
            new.__dict__["at"] = tuple(at)
        if confidence is not None:
            _check_confidence(self.id, confidence)
            new.__dict__["confidence"] = confidence
        return new

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["confidence"] = self.confidence
        if self.edge:
            d["edge"] = True
        return d


@dataclass(frozen=True)
class EnvObstacle:
    """A fixed feature (electrode, aggregate, debris) as a polygon with a height in nm."""

    polygon: tuple[Point, ...]
    height: float
    edge: bool = False

    def to_dict(self) -> dict:
        d: dict = {"polygon": [list(p) for p in self.polygon], "height": self.height}
        if self.edge:
            d["edge"] = True
        return d


@dataclass(frozen=True)
class Environment:
    """What identification found: ``area`` (w, h) in nm, objects and obstacles, positions
    relative to the scan's lower-left corner, which lies at ``origin`` in the scan file's
    own coordinates (an absolute-coordinate scan's offset; (0, 0) by default)."""

    area: Point
    objects: tuple[EnvObject, ...] = ()
    obstacles: tuple[EnvObstacle, ...] = ()
    source: str | None = None
    origin: Point = (0.0, 0.0)

    def to_dict(self) -> dict:
        d: dict = {"format": FORMAT}
        if self.source is not None:
            d["source"] = self.source
        d["area"] = list(self.area)
        d["objects"] = [o.to_dict() for o in self.objects]
        d["obstacles"] = [o.to_dict() for o in self.obstacles]
        if tuple(self.origin) != (0.0, 0.0):
            d["origin"] = list(self.origin)
        return d

    def dumps(self) -> str:
        return dumps_json(self.to_dict())

    def save(self, path: str | os.PathLike) -> None:
        write_atomic(path, self.dumps())

    def object(self, object_id: str) -> EnvObject:
        for o in self.objects:
            if o.id == object_id:
                return o
        raise KeyError(object_id)


def environment_from_dict(data: dict, source: str | None = None) -> Environment:
    """Validate a parsed ``nanoasm.env/1`` document; errors name ``source`` and the key."""
    check_format(data, source, FORMAT)
    t = Table(data, source)
    t.check_keys(required={"format", "area"}, optional={"source", "objects", "obstacles", "origin"})
    src = t.string("source", None)
    area = t.pair("area", names=("width", "height"), positive=True)
    origin = t.pair("origin", (0.0, 0.0))
    if max(abs(origin[0]), abs(origin[1])) > MAX_COORDINATE:
        t.fail("origin", f"({origin[0]:g}, {origin[1]:g}) lies beyond ±{MAX_COORDINATE:g} nm (1 m)")
    tables = t.tables("objects")
    objects = []
    for i, ot in enumerate(tables, start=1):
        body, _ = body_from_table(ot, f"o{i}", KINDS, extra=("confidence", "edge"))
        conf = ot.number("confidence", 1.0, lo=0.0, hi=1.0)
        edge = ot.boolean("edge", False)
        objects.append(EnvObject(body.id, body.kind, body.at, body.diameter, body.angle,
                                 body.length, conf, edge))
    check_unique_ids(tables, objects)
    obstacles = []
    for ot in t.tables("obstacles"):
        ot.check_keys(required={"polygon", "height"}, optional={"edge"})
        pts, _ = polygon_from_table(ot)
        height = ot.number("height", nonnegative=True)
        obstacles.append(EnvObstacle(pts, height, ot.boolean("edge", False)))
    return Environment(area, tuple(objects), tuple(obstacles), src, (float(origin[0]), float(origin[1])))


def load_environment(path: str | os.PathLike) -> Environment:
    """An environment file, validated, with everything in it inside its area
    (:func:`check_inside`)."""
    env = environment_from_dict(read_document(path), str(path))
    check_inside(env, str(path))
    return env


def check_inside(env: Environment, source: str | None) -> None:
    """Refuse an environment a scan could not have given: an area beyond any scanner's
    travel (``MAX_SCANNER_RANGE``), an object whose centre lies outside the area by more
    than its radius (half its length for a rod), or by more than its size when it is cut
    by the image border (``edge``: its centre is fitted to what the image shows of it),
    an object larger than the area, an obstacle vertex outside the area or an
    obstacle higher than ``MAX_HEIGHT``. One line naming ``source`` and the key.

    Only for files given to nanoasm: what a run logs may lie beyond a non-square area."""
    w, h = env.area
    if max(w, h) > MAX_SCANNER_RANGE:
        raise InputError(source, "area", f"{w:g} x {h:g} nm is beyond any scanner's travel: at most "
                                         f"{MAX_SCANNER_RANGE:g} nm a side (MAX_SCANNER_RANGE)")
    eps = TOUCH_EPS * max(w, h, 1.0)
    across = math.hypot(w, h)
    for i, o in enumerate(env.objects, start=1):
        size, name = (o.length, "length") if o.elongated else (o.diameter, "diameter")
        if size > across:
            raise InputError(source, f"objects[{i}].{name}", f"{size:g} nm is more than the area measures "
                                                             f"across ({across:.6g} nm)")
        (x, y), r = o.at, (size if o.edge else size / 2) + eps
        if not (-r <= x <= w + r and -r <= y <= h + r):
            raise InputError(source, f"objects[{i}].at", f"object {o.id!r} at ({x:g}, {y:g}) lies outside the "
                                                         f"area {w:g} x {h:g}")
    for k, ob in enumerate(env.obstacles, start=1):
        if ob.height > MAX_HEIGHT:
            raise InputError(source, f"obstacles[{k}].height", f"must be at most {MAX_HEIGHT:g} nm (1 mm), "
                                                               f"got {ob.height:g}")
        for j, (x, y) in enumerate(ob.polygon, start=1):
            if not (-eps <= x <= w + eps and -eps <= y <= h + eps):
                raise InputError(source, f"obstacles[{k}].polygon[{j}]", f"({x:g}, {y:g}) lies outside the "
                                                                         f"area {w:g} x {h:g}")
