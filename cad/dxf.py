"""DXF importer (ezdxf): CIRCLE -> particle slot, LINE -> rod slot, closed LWPOLYLINE
-> keep-out, a closed LWPOLYLINE on layer ``AREA`` -> working area.

- CIRCLE: particle at its centre, diameter ``2 r``.
- LINE: rod between its end points; the diameter is the ``rod_diameter`` option (in
  nm; DXF lines have no width). An open two-vertex LWPOLYLINE is a rod too, with its
  constant width as the diameter when it has one.
- closed LWPOLYLINE (closed flag, or last vertex on the first): keep-out polygon, arcs
  (bulges) flattened.
- closed LWPOLYLINE on the ``marks_layer`` (any case; none by default): alignment mark.
- closed LWPOLYLINE on layer ``AREA`` (any case): the working area, an axis-aligned
  rectangle whose lower-left corner is the origin; without one, ``area=(w, h)`` in nm
  with the origin at the drawing's (0, 0). Other entities on that layer are ignored.

Units: ``$INSUNITS`` when set (nm, µm, mm, cm, m, in, ...); ``scale`` (nm per drawing
unit) overrides it and is the only source for unitless drawings (default 1.0). Only
model space is read; block references (INSERT) are expanded with their transforms.

Expansion is budgeted before ezdxf builds anything (issue 15: a 30000 x 30000 MINSERT,
blocks nested 8 levels x 10 and huge-radius bulges each ran for minutes and gigabytes):
a block inserted in itself, nesting past :data:`MAX_DEPTH`, more than
:data:`MAX_INSTANCES` entities after expansion and more than :data:`MAX_ARC_POINTS`
points of flattened arcs are refused with one line.
"""

from __future__ import annotations

import logging
import math
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import NoReturn

import ezdxf
from ezdxf import recover
from ezdxf.entities import DXFGraphic
from ezdxf.path import make_path

from nanoasm.errors import InputError
from nanoasm.fileio import read_bytes

from .importers import (
    FLATTEN_NM,
    LayoutBuilder,
    Point,
    area_option,
    axis_rectangle,
    name_option,
    positive_option,
)

# ezdxf logs each repair of a damaged file as a warning, which Python's last-resort handler
# would print to stderr beside nanoasm's own line: the repairs are counted (a note) instead
logging.getLogger("ezdxf").addHandler(logging.NullHandler())

AREA_LAYER = "AREA"

#: Nanometres per drawing unit for each supported ``$INSUNITS`` code.
INSUNITS_NM = {
    1: 25.4e6,      # inch
    2: 304.8e6,     # foot
    4: 1e6,         # millimetre
    5: 1e7,         # centimetre
    6: 1e9,         # metre
    8: 25.4,        # microinch
    9: 25.4e3,      # mil
    11: 0.1,        # angstrom
    12: 1.0,        # nanometre
    13: 1e3,        # micrometre
    14: 1e8,        # decimetre
}

#: Deepest nesting of block references (an INSERT in a block inserted in a block ...).
#: CAD drawings nest a few levels; 16 leaves room and keeps ezdxf's expansion shallow.
MAX_DEPTH = 16
#: Most entities after expanding every block reference (a MINSERT counts rows x columns,
#: nested blocks multiply; model-space entities count too). ezdxf builds about 20 000
#: virtual entities a second here, so 100 000 is ~5 s and ~300 MB; the 30000 x 30000
#: MINSERT of issue 15 asks for 9 x 10^8.
MAX_INSTANCES = 100_000
#: Most points the arcs (LWPOLYLINE bulges) of the whole drawing may be flattened into at
#: FLATTEN_NM. An arc of radius r and angle a needs about a / sqrt(8 FLATTEN_NM / r)
#: points: a full circle of 1 mm radius ~2 200, of 100 um ~700; a bulge with a radius of
#: 10^15 nm would need 10^8 (issue 15: a MemoryError after 43 s).
MAX_ARC_POINTS = 200_000

_BINARY_SENTINEL = b"AutoCAD Binary DXF"


def import_dxf(path: str | os.PathLike, *, scale: float | None = None,
               rod_diameter: float | None = None, area: tuple[float, float] | None = None,
               marks_layer: str | None = None, warnings: list[str] | None = None) -> dict:
    """Read a DXF drawing as a layout v1 dict.

    Parameters
    ----------
    path : str or path-like
        The DXF file (text or binary).
    scale : float, optional
        Nanometres per drawing unit; overrides ``$INSUNITS``.
    rod_diameter : float, optional
        Diameter (nm) of the rods drawn as LINEs.
    area : (float, float), optional
        Working area (nm) when the drawing has no rectangle on layer ``AREA``.
    marks_layer : str, optional
        Layer (any case) whose closed LWPOLYLINEs are alignment marks; none by default.
    warnings : list of str, optional
        Receives a line per kind of ignored entity and about repairs ezdxf made.
    """
    src = str(path)
    scale = positive_option("scale", scale) if scale is not None else None
    rod_diameter = positive_option("rod_diameter", rod_diameter) if rod_diameter is not None else None
    size = area_option(area) if area is not None else None
    binary = _check_bytes(read_bytes(path), src)
    doc, repairs = _read(path, src, binary)
    builder = _Mapper(src, Path(path).stem, _nm_per_unit(doc, scale, src), rod_diameter)
    builder.marks_layer = None if marks_layer is None else name_option("marks_layer", marks_layer).upper()
    code = doc.header.get("$INSUNITS", 0)
    builder.units = (f"--scale {scale:g} nm per drawing unit" if scale is not None
                     else f"$INSUNITS = {code}, {builder.unit:g} nm per drawing unit (--scale overrides it)" if code
                     else "a unitless drawing at 1 nm per unit (--scale sets it)")
    if repairs:
        builder.notes.append(f"{src}: ezdxf repaired {repairs} problem(s) in the file")
    layout = builder.run(doc, size)
    builder.report(warnings)
    return layout


# -- reading ------------------------------------------------------------------------

def _check_bytes(raw: bytes, src: str) -> bool:
    """Refuse files ezdxf's recover mode would turn into an empty drawing; whether the
    file is a binary DXF."""
    if raw.startswith(_BINARY_SENTINEL):
        if not raw.rstrip(b"\x00").endswith(b"EOF"):
            raise InputError(src, None, "truncated binary DXF file (it does not end with EOF)")
        return True
    if b"\x00" in raw:
        raise InputError(src, None, "binary file, expected DXF")
    lines = [ln.strip() for ln in raw.splitlines() if ln.strip()]
    if len(lines) < 2 or lines[0] not in (b"0", b"999"):
        head = lines[0][:30].decode("utf-8", "replace") if lines else ""
        raise InputError(src, None, f"not a DXF file (it starts with {head!r})")
    if lines[-2:] != [b"0", b"EOF"]:
        raise InputError(src, None, "truncated DXF file (it does not end with 0/EOF)")
    return False


def _read(path: str | os.PathLike, src: str, binary: bool) -> tuple[ezdxf.document.Drawing, int]:
    """The drawing (text files in recover mode) and the number of problems ezdxf repaired."""
    try:
        if binary:  # recover mode reads text DXF only
            doc = ezdxf.readfile(str(path))
            auditor = doc.audit()
        else:
            doc, auditor = recover.readfile(str(path))
    except ezdxf.DXFStructureError as exc:
        raise InputError(src, None, f"damaged DXF file: {exc}") from None
    except (ezdxf.DXFError, OSError, UnicodeError, ValueError, IndexError, struct.error) as exc:
        raise InputError(src, None, f"cannot read DXF: {exc}") from None
    except (AttributeError, TypeError, KeyError, AssertionError) as exc:
        # ezdxf's recover mode and audit trust some structures of a damaged file (a layout
        # without its attributes): their failure is the file's
        raise InputError(src, None, f"damaged DXF file ezdxf cannot repair ({type(exc).__name__}: {exc})") from None
    return doc, len(auditor.fixes) + len(auditor.errors)


def _nm_per_unit(doc: ezdxf.document.Drawing, scale: float | None, src: str) -> float:
    if scale is not None:
        return scale
    code = doc.header.get("$INSUNITS", 0)
    if not code:
        return 1.0
    if code not in INSUNITS_NM:
        raise InputError(src, "$INSUNITS", f"unsupported drawing unit code {code!r}; give --scale "
                                           "(nm per drawing unit)")
    return INSUNITS_NM[code]


# -- mapping ------------------------------------------------------------------------

class _Mapper(LayoutBuilder):
    """A :class:`LayoutBuilder` that knows the drawing's units and rod diameter."""

    def __init__(self, source: str, name: str, unit: float, rod_diameter: float | None):
        super().__init__(source, name)
        self.unit = unit
        self.rod_diameter = rod_diameter
        self.origin: Point = (0.0, 0.0)
        self.arc_points = 0     # estimated points of the arcs flattened so far
        self.marks_layer: str | None = None     # upper case

    def nm(self, p) -> Point:
        """Drawing coordinates -> layout nm."""
        return (float(p[0]) - self.origin[0]) * self.unit, (float(p[1]) - self.origin[1]) * self.unit

    def run(self, doc: ezdxf.document.Drawing, size: Point | None) -> dict:
        _Expansion(doc, self.source).check(doc.modelspace())
        entities = list(_entities(doc.modelspace(), self.source))
        size = self._area(entities, size)
        for key, e in entities:
            self._entity(key, e)
        return self.build(size, "expected CIRCLE entities for particles or LINE entities for rods")

    def _area(self, entities: list[tuple[str, DXFGraphic]], size: Point | None) -> Point:
        rects = [(k, e) for k, e in entities if _on_area_layer(e) and _is_closed_polyline(e)]
        if len(rects) > 1:
            self.fail(f"layer {AREA_LAYER}", f"{len(rects)} closed polylines; expected one rectangle")
        if not rects:
            if size is None:
                self.fail(None, f"no working area: draw a closed rectangle (LWPOLYLINE) on layer "
                                f"{AREA_LAYER} or give --area W H")
            return size
        key, e = rects[0]
        if size is not None:
            self.fail("--area", f"the drawing already has a working area on layer {AREA_LAYER}; drop --area")
        self._planar(key, e)
        rect = axis_rectangle((v.x, v.y) for v in e.vertices_in_wcs())
        if rect is None or any(b for *_, b in e.get_points("xyb")):
            self.fail(key, "the working area must be an axis-aligned rectangle")
        x0, y0, w, h = rect
        if not all(math.isfinite(v) for v in rect):
            self.fail(key, "working area is not finite")
        self.origin = (x0, y0)
        return w * self.unit, h * self.unit

    def _entity(self, key: str, e: DXFGraphic) -> None:
        kind = e.dxftype()
        if _on_area_layer(e):
            if not (kind == "LWPOLYLINE" and _is_closed_polyline(e)):
                self.ignore(f"{kind} on layer {AREA_LAYER}")
        elif self.marks_layer is not None and str(e.dxf.get("layer", "0")).upper() == self.marks_layer:
            if kind == "LWPOLYLINE" and _is_closed_polyline(e):
                self._polyline(key, e, mark=True)
            else:
                self.ignore(f"{kind} on the marks layer")
        elif kind == "CIRCLE":
            self._circle(key, e)
        elif kind == "LINE":
            self._rod(key, e.dxf.start, e.dxf.end, None)
        elif kind == "LWPOLYLINE":
            self._polyline(key, e)
        else:
            self.ignore(kind)

    def _planar(self, key: str, e: DXFGraphic) -> None:
        ext = e.dxf.get("extrusion", (0.0, 0.0, 1.0))
        if not all(math.isfinite(v) for v in ext) or math.hypot(ext[0], ext[1]) > 1e-9 * abs(ext[2]):
            self.fail(key, "entity is not in the XY plane")

    def _circle(self, key: str, e: DXFGraphic) -> None:
        r = e.dxf.radius
        if not math.isfinite(r) or r <= 0:
            self.fail(key, f"radius must be a positive number, got {r:g}")
        self._planar(key, e)
        self.particle(key, self.nm(e.ocs().to_wcs(e.dxf.center)), 2 * r * self.unit)

    def _rod(self, key: str, start, end, width: float | None) -> None:
        if width:
            diameter = width * self.unit
        elif self.rod_diameter is not None:
            diameter = self.rod_diameter
        else:
            self.fail(key, "no rod diameter (DXF lines have no width); give --rod-diameter")
        self.rod(key, self.nm(start), self.nm(end), diameter)

    def _polyline(self, key: str, e: DXFGraphic, *, mark: bool = False) -> None:
        self._planar(key, e)
        if _is_closed_polyline(e):
            self._arc_budget(key, e)
            try:
                points = list(make_path(e).flattening(FLATTEN_NM / self.unit, segments=8))
            except (ValueError, ZeroDivisionError, ArithmeticError) as exc:
                self.fail(key, f"cannot flatten the outline ({exc})")
            self.keepout(key, [self.nm(p) for p in points], what="mark" if mark else "keep-out")
        elif len(e) == 2:
            if any(b for *_, b in e.get_points("xyb")):
                self.fail(key, "a rod polyline must be straight (it has an arc segment)")
            width = float(e.dxf.const_width)
            if not math.isfinite(width) or width < 0:
                self.fail(key, f"width must be a positive number, got {width:g}")
            start, end = e.vertices_in_wcs()
            self._rod(key, start, end, width)
        else:
            self.ignore("open LWPOLYLINE")

    def _arc_budget(self, key: str, e: DXFGraphic) -> None:
        """Refuse a closed polyline whose bulges would flatten into more points than
        :data:`MAX_ARC_POINTS` leaves (estimated before ezdxf flattens them)."""
        points = [(float(x), float(y), float(b)) for x, y, b in e.get_points("xyb")]
        tol = FLATTEN_NM / self.unit
        for (x0, y0, bulge), (x1, y1, _) in zip(points, points[1:] + points[:1]):
            if not bulge:
                continue
            if not all(math.isfinite(v) for v in (x0, y0, x1, y1, bulge)):
                self.fail(key, "a vertex or bulge is not finite")
            angle = 4 * math.atan(abs(bulge))
            chord = math.hypot(x1 - x0, y1 - y0)
            radius = chord / (2 * math.sin(angle / 2)) if chord else 0.0
            if radius > tol:
                self.arc_points += math.ceil(angle / (2 * math.acos(1 - tol / radius)))
            if not self.arc_points <= MAX_ARC_POINTS:
                self.fail(key, f"flattening its arcs (one of radius {radius * self.unit:.3g} nm) "
                               f"would take the drawing past the {MAX_ARC_POINTS} arc points the "
                               f"importer allows at {FLATTEN_NM:g} nm")


class _Expansion:
    """Counts what expanding the block references would give, without building it:
    refuses a block inserted in itself, nesting past :data:`MAX_DEPTH` and more than
    :data:`MAX_INSTANCES` entities. Each block is counted once."""

    def __init__(self, doc: ezdxf.document.Drawing, src: str):
        self.doc = doc
        self.src = src
        self.done: dict[str, tuple[int, int]] = {}          # block -> (entities, depth)
        self.path: list[str] = []
        self.key = ""

    def check(self, modelspace) -> None:
        total = 0
        for e in modelspace:
            handle = e.dxf.get("handle")
            self.key = f"{e.dxftype()}" + (f" {handle}" if handle else "")
            total += self._entity(e)[0]
            if total > MAX_INSTANCES:
                what = (f"expanding its block{self._grid(e)} would take the drawing past"
                        if e.dxftype() == "INSERT" else "the drawing has more than")
                self.fail(f"{what} the {MAX_INSTANCES} entities the importer allows "
                          "(after expanding blocks and MINSERT arrays)")

    def fail(self, problem: str) -> NoReturn:
        raise InputError(self.src, self.key, problem)

    @staticmethod
    def _copies(e: DXFGraphic) -> int:
        """How many inserts ezdxf makes of an INSERT (its MINSERT loop runs rows x
        columns times whenever ``mcount`` > 1, even when a spacing is 0)."""
        if e.mcount <= 1:
            return 1
        return max(1, max(0, int(e.dxf.row_count)) * max(0, int(e.dxf.column_count)))

    def _grid(self, e: DXFGraphic) -> str:
        if e.dxftype() != "INSERT":
            return ""
        name = e.dxf.get("name", "?")
        if self._copies(e) > 1:
            return f" {name} ({e.dxf.row_count} x {e.dxf.column_count} MINSERT)"
        return f" {name}"

    def _entity(self, e: DXFGraphic) -> tuple[int, int]:
        """(entities, depth) one entity expands to."""
        if e.dxftype() != "INSERT":
            return 1, 0
        block = self.doc.blocks.get(e.dxf.get("name", ""))
        if block is None:                                   # ezdxf expands it to nothing
            return 1, 0
        n, depth = self._block(block)
        return self._copies(e) * (1 + n), depth + 1

    def _block(self, block) -> tuple[int, int]:
        name = block.name.lower()
        if name in self.done:
            n, depth = self.done[name]
            if len(self.path) + depth + 1 > MAX_DEPTH:
                self._too_deep(block.name)
            return n, depth
        if name in (p.lower() for p in self.path):
            start = [p.lower() for p in self.path].index(name)
            self.fail(f"block {block.name} is inserted in itself "
                      f"({' > '.join([*self.path[start:], block.name])})")
        self.path.append(block.name)
        if len(self.path) > MAX_DEPTH:
            self._too_deep(None)
        total, deepest = 0, 0
        for e in block:
            n, depth = self._entity(e)
            total += n
            deepest = max(deepest, depth)
            if total > MAX_INSTANCES:
                via = f"; inserted via {' > '.join(self.path)}" if len(self.path) > 1 else ""
                self.fail(f"block {block.name} expands to more than the {MAX_INSTANCES} "
                          f"entities the importer allows (after expanding blocks and MINSERT arrays{via})")
        self.path.pop()
        self.done[name] = (total, deepest)
        return total, deepest

    def _too_deep(self, more: str | None) -> NoReturn:
        chain = [*self.path, *([more] if more else [])]
        if len(chain) > 6:
            chain = [*chain[:3], "...", *chain[-2:]]
        self.fail(f"block references are nested more than {MAX_DEPTH} deep ({' > '.join(chain)})")


def _on_area_layer(e: DXFGraphic) -> bool:
    return str(e.dxf.get("layer", "0")).upper() == AREA_LAYER


def _is_closed_polyline(e: DXFGraphic) -> bool:
    if e.dxftype() != "LWPOLYLINE" or len(e) < 3:
        return False
    points = e.get_points("xy")
    return bool(e.closed) or tuple(points[0]) == tuple(points[-1])


def _entities(space, src: str, prefix: str = "", depth: int = 0) -> Iterator[tuple[str, DXFGraphic]]:
    """``(key, entity)`` for every entity, block references expanded in place."""
    if depth > MAX_DEPTH:
        raise InputError(src, prefix.rstrip(" >"), "block references are nested too deeply")
    for e in space:
        handle = e.dxf.get("handle")
        key = f"{prefix}{e.dxftype()}" + (f" {handle}" if handle else "")
        if e.dxftype() == "INSERT":
            try:
                inserts = list(e.multi_insert()) if e.mcount > 1 else [e]  # MINSERT arrays
                parts = [part for ins in inserts for part in ins.virtual_entities()]
            except (ezdxf.DXFError, ValueError, ArithmeticError) as exc:
                raise InputError(src, key, f"cannot expand the block reference ({exc})") from None
            yield from _entities(parts, src, f"{key} > ", depth + 1)
        else:
            yield key, e
