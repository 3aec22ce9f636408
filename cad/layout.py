"""Layout v1 (``nanoasm.layout/1``): which object goes where.

A layout is a working area, target slots (particles and rods), keep-out polygons and
alignment marks (``[[mark]]``: features that exist on the sample, keep-outs too, by which
the layout is registered to a scan: :mod:`nanoasm.planner.alignment`), loaded from TOML
or JSON into frozen, validated value types. Every rejection is an
:class:`~nanoasm.errors.InputError` naming the file, the key path and the problem.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

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

from .frame import Similarity

FORMAT = "nanoasm.layout/1"
KINDS = ("particle", "rod")

#: Most targets a layout may have (checked before any is read). Every slot costs a check
#: scan at the run's end and its object a few pushes with local scans around each, some
#: 30 s of instrument time: 10 000 slots are about four days. Real layouts have tens to
#: thousands; a dry-run of 100 000 ran out of 3 GB after 52 s (issue 15).
MAX_TARGETS = 10_000

#: A side of a working area (nm) beyond which its units are likely wrong (1 mm, more
#: than any AFM scanner's range): the refusal says so.
IMPLAUSIBLE_SIDE = 1e6

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
    """A layout. ``marks`` are alignment marks (features on the sample, keep-outs too);
    ``registration`` is set on a layout :meth:`mapped` from its own frame into a scan's
    (None: the layout is in its own frame)."""

    area: Point
    targets: tuple[Target, ...]
    keepouts: tuple[Keepout, ...] = ()
    tolerance: Tolerance = field(default_factory=Tolerance)
    name: str | None = None
    marks: tuple[Keepout, ...] = ()
    registration: Similarity | None = None

    def to_dict(self) -> dict:
        d: dict = {"format": FORMAT}
        if self.name is not None:
            d["name"] = self.name
        d["area"] = list(self.area)
        d["tolerance"] = self.tolerance.to_dict()
        d["target"] = [t.to_dict() for t in self.targets]
        if self.keepouts:
            d["keepout"] = [k.to_dict() for k in self.keepouts]
        if self.marks:
            d["mark"] = [m.to_dict() for m in self.marks]
        return d

    @property
    def regions(self) -> tuple[Keepout, ...]:
        """Every region no object may enter: the keep-outs, then the marks."""
        return self.keepouts + self.marks

    def mapped(self, transform: Similarity, area: Point) -> Layout:
        """This layout (in its own frame) moved into a scan's frame by ``transform``, with
        the scan's ``area``: slots, keep-outs and marks mapped; the result records the
        transform as its ``registration``. Not validated again (slots may leave the area:
        :func:`nanoasm.planner.frames.check_in_area` says so)."""
        return replace(self, area=(float(area[0]), float(area[1])),
                       targets=tuple(transform.body(t) for t in self.targets),
                       keepouts=tuple(Keepout(transform.polygon(k.polygon)) for k in self.keepouts),
                       marks=tuple(Keepout(transform.polygon(m.polygon)) for m in self.marks),
                       registration=transform)


    def target(self, target_id: str) -> Target:
        for t in self.targets:
            if t.id == target_id:
                return t
        raise KeyError(target_id)

    def summary(self) -> str:
        n_p = sum(t.kind == "particle" for t in self.targets)
        n_r = sum(t.kind == "rod" for t in self.targets)
        label = f"{self.name!r}: " if self.name else ""
        marks = f", {len(self.marks)} mark(s)" if self.marks else ""
        return (f"{label}{self.area[0]:g} x {self.area[1]:g} nm, {n_p} particle slot(s), "
                f"{n_r} rod slot(s), {len(self.keepouts)} keep-out(s){marks}")


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
            units = (f"; {side / 1e6:g} mm is no AFM's working area: are the units right (a CAD drawing's "
                     "unit, or --scale)?" if side > IMPLAUSIBLE_SIDE else "")
            t.fail("area", f"{name} {side:g} nm is more than a run can scan: at most {MAX_LAYOUT_SIDE:g} nm "
                           f"(MAX_LAYOUT_SIDE: 4096 pixels of the full scan's 10 nm){units}")


def layout_from_dict(data: dict, source: str | None = None) -> Layout:
    """Validate a parsed layout document (TOML, JSON or an importer's output)."""
    check_format(data, source, FORMAT)
    t = Table(data, source)
    t.check_keys(required={"format", "area"}, optional={"name", "tolerance", "target", "keepout", "mark"})
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

    ktables, mtables = t.tables("keepout"), t.tables("mark")
    keepouts, polys = [], []
    for kt in ktables + mtables:            # a mark is a keep-out too
        kt.check_keys(required={"polygon"})
        pts, poly = polygon_from_table(kt)
        keepouts.append(Keepout(pts))
        polys.append(poly)

    check_placement("target", ttables, targets, area, ktables + mtables, polys)

    n = len(ktables)
    return Layout(area, tuple(targets), tuple(keepouts[:n]), tolerance, name, tuple(keepouts[n:]))


def load_layout(path: str | os.PathLike) -> Layout:
    """Load a layout from TOML or JSON (by suffix, else by content)."""
    return layout_from_dict(read_document(path), str(path))
