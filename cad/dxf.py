"""DXF importer (ezdxf): CIRCLE -> particle slot, LINE -> rod slot, closed LWPOLYLINE
-> keep-out, a closed LWPOLYLINE on layer ``AREA`` -> working area.

- CIRCLE: particle at its centre, diameter ``2 r``.
- LINE: rod between its end points; the diameter is the ``rod_diameter`` option (in
  nm; DXF lines have no width). An open two-vertex LWPOLYLINE is a rod too, with its
  constant width as the diameter when it has one.
- closed LWPOLYLINE (closed flag, or last vertex on the first): keep-out polygon, arcs
  (bulges) flattened.
- closed LWPOLYLINE on layer ``AREA`` (any case): the working area, an axis-aligned
  rectangle whose lower-left corner is the origin; without one, ``area=(w, h)`` in nm
  with the origin at the drawing's (0, 0). Other entities on that layer are ignored.

Units: ``$INSUNITS`` when set (nm, µm, mm, cm, m, in, ...); ``scale`` (nm per drawing
unit) overrides it and is the only source for unitless drawings (default 1.0). Only
model space is read; block references (INSERT) are expanded with their transforms.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Iterator
from pathlib import Path

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
    positive_option,
)

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

_BINARY_SENTINEL = b"AutoCAD Binary DXF"
_MAX_BLOCK_DEPTH = 16


def import_dxf(path: str | os.PathLike, *, scale: float | None = None,
               rod_diameter: float | None = None, area: tuple[float, float] | None = None,
               warnings: list[str] | None = None) -> dict:
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

    def nm(self, p) -> Point:
        """Drawing coordinates -> layout nm."""
        return (float(p[0]) - self.origin[0]) * self.unit, (float(p[1]) - self.origin[1]) * self.unit

    def run(self, doc: ezdxf.document.Drawing, size: Point | None) -> dict:
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

    def _polyline(self, key: str, e: DXFGraphic) -> None:
        self._planar(key, e)
        if _is_closed_polyline(e):
            try:
                points = list(make_path(e).flattening(FLATTEN_NM / self.unit, segments=8))
            except (ValueError, ZeroDivisionError, ArithmeticError) as exc:
                self.fail(key, f"cannot flatten the outline ({exc})")
            self.keepout(key, [self.nm(p) for p in points])
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


def _on_area_layer(e: DXFGraphic) -> bool:
    return str(e.dxf.get("layer", "0")).upper() == AREA_LAYER


def _is_closed_polyline(e: DXFGraphic) -> bool:
    if e.dxftype() != "LWPOLYLINE" or len(e) < 3:
        return False
    points = e.get_points("xy")
    return bool(e.closed) or tuple(points[0]) == tuple(points[-1])


def _entities(space, src: str, prefix: str = "", depth: int = 0) -> Iterator[tuple[str, DXFGraphic]]:
    """``(key, entity)`` for every entity, block references expanded in place."""
    if depth > _MAX_BLOCK_DEPTH:
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
