"""Layout v1 (``nanoasm.layout/1``): which object goes where.

A layout is a working area, target slots (particles and rods) and keep-out polygons,
loaded from TOML or JSON into frozen, validated value types. Every rejection is an
:class:`~nanoasm.errors.InputError` naming the file, the key path and the problem.
"""

from __future__ import annotations

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
from nanoasm.world.limits import MAX_LAYOUT_SIDE

FORMAT = "nanoasm.layout/1"
KINDS = ("particle", "rod")

#: Most targets a layout may have (checked before any is read). Every slot costs a check
#: scan at the run's end and its object a few pushes with local scans around each, some
#: 30 s of instrument time: 10 000 slots are about four days. Real layouts have tens to
#: thousands; a dry-run of 100 000 ran out of 3 GB after 52 s (issue 15).
MAX_TARGETS = 10_000

Target = Body


@dataclass(frozen=True)
class Tolerance:
    """When a slot counts as filled: centre error (nm), rod axis error (deg), relative size."""

    position: float = 20.0
    angle: float = 3.0
    size: float = 0.25

    def to_dict(self) -> dict:
        return {"position": self.position, "angle": self.angle, "size": self.size}


def size_ok(target: Body, obj: Body, tol: Tolerance) -> bool:
    """Whether ``obj`` has the target's size within ``tol.size`` (relative diameter, and
    relative length for a rod)."""
    if abs(obj.diameter - target.diameter) > tol.size * target.diameter:
        return False
    if target.kind == "rod" and abs(obj.length - target.length) > tol.size * target.length:
        return False
    return True


@dataclass(frozen=True)
class Keepout:
    """A region no object may enter (electrodes, marks), as polygon vertices in nm."""

    polygon: tuple[Point, ...]

    def geometry(self) -> shapely.Polygon:
        return polygon_geometry(self.polygon)

    def to_dict(self) -> dict:
        return {"polygon": [list(p) for p in self.polygon]}


@dataclass(frozen=True)
class Layout(Document):
    area: Point
    targets: tuple[Target, ...]
    keepouts: tuple[Keepout, ...] = ()
    tolerance: Tolerance = field(default_factory=Tolerance)
    name: str | None = None

    def to_dict(self) -> dict:
        d: dict = {"format": FORMAT}
        if self.name is not None:
            d["name"] = self.name
        d["area"] = list(self.area)
        d["tolerance"] = self.tolerance.to_dict()
        d["target"] = [t.to_dict() for t in self.targets]
        if self.keepouts:
            d["keepout"] = [k.to_dict() for k in self.keepouts]
        return d


    def target(self, target_id: str) -> Target:
        for t in self.targets:
            if t.id == target_id:
                return t
        raise KeyError(target_id)

    def summary(self) -> str:
        n_p = sum(t.kind == "particle" for t in self.targets)
        n_r = sum(t.kind == "rod" for t in self.targets)
        label = f"{self.name!r}: " if self.name else ""
        return (f"{label}{self.area[0]:g} x {self.area[1]:g} nm, {n_p} particle slot(s), "
                f"{n_r} rod slot(s), {len(self.keepouts)} keep-out(s)")


def _tolerance(t: Table) -> Tolerance:
    tt = t.table("tolerance", optional=True)
    if tt is None:
        return Tolerance()
    tt.check_keys(optional={"position", "angle", "size"})
    d = Tolerance()
    return Tolerance(
        position=tt.number("position", d.position, positive=True),
        angle=tt.number("angle", d.angle, positive=True, hi=90.0),
        size=tt.number("size", d.size, positive=True, hi=1.0),
    )


def _check_side(t: Table, area: Point) -> None:
    """A working area no larger than a run can scan: each side at most ``MAX_LAYOUT_SIDE``."""
    for side, name in zip(area, ("width", "height")):
        if side > MAX_LAYOUT_SIDE:
            t.fail("area", f"{name} {side:g} nm is more than a run can scan: at most {MAX_LAYOUT_SIDE:g} nm "
                           "(MAX_LAYOUT_SIDE: 4096 pixels of the full scan's 10 nm)")


def layout_from_dict(data: dict, source: str | None = None) -> Layout:
    """Validate a parsed layout document (TOML, JSON or an importer's output)."""
    check_format(data, source, FORMAT)
    t = Table(data, source)
    t.check_keys(required={"format", "area"}, optional={"name", "tolerance", "target", "keepout"})
    name = t.string("name", None)
    area = t.pair("area", names=("width", "height"), positive=True)
    _check_side(t, area)
    tolerance = _tolerance(t)

    ttables = t.tables("target")
    if not ttables:
        t.fail("target", "a layout needs at least one [[target]]")
    if len(ttables) > MAX_TARGETS:
        t.fail("target", f"{len(ttables)} targets; a layout may have at most {MAX_TARGETS} (MAX_TARGETS)")
    targets = [body_from_table(tt, f"t{i}", KINDS)[0] for i, tt in enumerate(ttables, start=1)]
    check_unique_ids(ttables, targets)

    ktables = t.tables("keepout")
    keepouts, polys = [], []
    for kt in ktables:
        kt.check_keys(required={"polygon"})
        pts, poly = polygon_from_table(kt)
        keepouts.append(Keepout(pts))
        polys.append(poly)

    check_placement("target", ttables, targets, area, ktables, polys)

    return Layout(area, tuple(targets), tuple(keepouts), tolerance, name)


def load_layout(path: str | os.PathLike) -> Layout:
    """Load a layout from TOML or JSON (by suffix, else by content)."""
    return layout_from_dict(read_document(path), str(path))
