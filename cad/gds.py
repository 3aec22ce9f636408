"""GDSII importer (gdstk): the layer/datatype of each shape gives its role.

Defaults (each an option):

- particles ``1/0``: polygons approximating circles; centre and diameter from a
  least-squares circle through the vertices (exact for the usual polygons, whose
  vertices lie on the circle, however few); a polygon with fewer than 6 corners or
  whose vertices stray from a circle is refused.
- rods ``2/0``: a straight PATH (centre, angle and length from its spine, diameter =
  its width; round or extended ends add their extension to the length) or a
  rectangle polygon (long side = length, short side = diameter).
- keep-outs ``3/0``: polygons (paths there count as their outlines).
- alignment marks: none by default; ``marks_layer`` names their layer (polygons, as
  keep-outs).
- working area ``0/0``: one axis-aligned rectangle; its lower-left corner is the
  origin. Without it, ``area=(w, h)`` in nm with the origin at the file's (0, 0).

The top cell is used (or ``cell``), with references and arrays flattened. Coordinates
are converted to nm with the library's unit. Other layers and text labels are ignored.

Before gdstk flattens anything, the reference hierarchy below the top cell is walked
here (issue 15: gdstk crashes with SIGSEGV on a cyclic reference, on an array of
32767 x 32767 and on deep nesting): a cycle, nesting deeper than :data:`MAX_DEPTH`, more
than :data:`MAX_INSTANCES` instances or :data:`MAX_VERTICES` vertices after flattening
are refused with one line.
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import warnings
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import NoReturn

import gdstk
import numpy as np

from nanoasm.errors import InputError
from nanoasm.fileio import read_bytes

from .importers import (
    LayoutBuilder,
    Point,
    area_option,
    axis_rectangle,
    flag,
    layer_option,
    name_option,
    ring,
)

Layer = tuple[int, int]

#: Fewest corners of a particle polygon (a square or a triangle is not a particle).
MIN_CORNERS = 6
#: Largest deviation of a particle polygon's vertices from the fitted circle, relative.
ROUND_TOL = 0.05
#: Largest angle (degrees) around the centre between neighbouring particle vertices.
MAX_GAP_DEG = 90.0
#: Rod rectangles: largest |cos| of a corner angle and relative mismatch of opposite sides.
RECT_TOL = 0.05

#: Deepest nesting of cell references below the top cell. Real layouts nest a few
#: levels (rarely 20); gdstk flattens recursively in C++, and a chain nested deep enough
#: overflows its stack (SIGSEGV, no message).
MAX_DEPTH = 64
#: Most instances after flattening: every shape, label and cell placement counts once
#: per time it is placed (an AREF counts columns x rows; nested arrays multiply). A
#: million flatten in about a second and well under 1 GB; the 550-byte AREF of
#: 32767 x 32767 in issue 15 asks for 10^9 and made gdstk segfault.
MAX_INSTANCES = 1_000_000
#: Most vertices, after flattening, of the shapes on the particle, rod, keep-out and
#: area layers (only these are flattened; round path ends counted as gdstk will draw
#: them). Joining split particle polygons costs ~300 bytes a vertex, so a million stay
#: near 350 MB and a few seconds; 5 000 particles of 200 vertices fit.
MAX_VERTICES = 1_000_000

# GDSII record types and the byte size of each data type (0: no data ... 6: ASCII).
_HEADER, _ENDLIB = 0x00, 0x04
_STRNAME, _XY, _ENDEL, _SNAME, _COLROW = 0x06, 0x10, 0x11, 0x12, 0x13
#: Element records (BOUNDARY, PATH, SREF, AREF, TEXT, NODE, BOX) and the records each must
#: hold before its ENDEL: gdstk reads an element without them from memory it never filled
#: (a BOUNDARY without XY segfaulted).
_ELEMENT_NEEDS = {0x08: {_XY}, 0x09: {_XY}, 0x0A: {_XY, _SNAME}, 0x0B: {_XY, _SNAME, _COLROW},
                  0x0C: {_XY}, 0x15: {_XY}, 0x2D: {_XY}}
_DATA_SIZE = {0: 0, 1: 2, 2: 2, 3: 4, 4: 4, 5: 8, 6: 1}


def import_gds(path: str | os.PathLike, *, cell: str | None = None,
               area: tuple[float, float] | None = None,
               particle_layer: Layer | str = (1, 0), rod_layer: Layer | str = (2, 0),
               keepout_layer: Layer | str = (3, 0), area_layer: Layer | str = (0, 0),
               marks_layer: Layer | str | None = None, warnings: list[str] | None = None) -> dict:
    """Read a GDSII layout as a layout v1 dict.

    Parameters
    ----------
    path : str or path-like
        The GDSII stream file.
    cell : str, optional
        Cell to read; default: the library's only top cell.
    area : (float, float), optional
        Working area (nm) when the file has no rectangle on ``area_layer``.
    particle_layer, rod_layer, keepout_layer, area_layer : (int, int) or "L/D"
        Layer and datatype of each role.
    marks_layer : (int, int) or "L/D", optional
        Layer and datatype of alignment marks (polygons, as keep-outs); none by default.
    warnings : list of str, optional
        Receives a line per kind of ignored shape.
    """
    src = str(path)
    roles = {"particle": layer_option("particle_layer", particle_layer),
             "rod": layer_option("rod_layer", rod_layer),
             "keepout": layer_option("keepout_layer", keepout_layer),
             "area": layer_option("area_layer", area_layer)}
    if marks_layer is not None:
        roles["marks"] = layer_option("marks_layer", marks_layer)
    _check_distinct(roles)
    size = area_option(area) if area is not None else None
    cell = name_option("cell", cell) if cell is not None else None
    _check_records(read_bytes(path), src)
    lib, skipped = _read(path, src)
    top = _top_cell(lib, cell, src)
    tally = _Hierarchy(src, set(roles.values())).tally(top)
    builder = LayoutBuilder(src, Path(path).stem)
    builder.notes.extend(f"{src}: gdstk: {message} ({n} time(s))" for message, n in sorted(skipped.items()))
    origin, size = _working_area(top, roles["area"], size, builder)
    _particles(top, roles["particle"], origin, builder)
    _rods(top, roles["rod"], origin, builder)
    for poly in top.get_polygons(include_paths=True, layer=roles["keepout"][0], datatype=roles["keepout"][1]):
        builder.keepout(_key("polygon", roles["keepout"], poly.points),
                        [_shift(p, origin) for p in poly.points])
    if "marks" in roles:
        m = roles["marks"]
        for poly in top.get_polygons(include_paths=True, layer=m[0], datatype=m[1]):
            builder.mark(_key("polygon", m, poly.points), [_shift(p, origin) for p in poly.points])
    _count_ignored(tally, set(roles.values()), builder)
    p, r = roles["particle"], roles["rod"]
    layout = builder.build(size, f"expected circle polygons on layer {p[0]}/{p[1]} "
                                 f"or paths/rectangles on layer {r[0]}/{r[1]}")
    builder.report(warnings)
    return layout


# -- reading ------------------------------------------------------------------------

def _check_distinct(roles: dict[str, Layer]) -> None:
    seen: dict[Layer, str] = {}
    for role, layer in roles.items():
        if layer in seen:
            raise InputError(None, flag(f"{role}_layer"), f"is the same layer {layer[0]}/{layer[1]} "
                                                          f"as {flag(seen[layer] + '_layer')}")
        seen[layer] = role


def _check_records(raw: bytes, src: str) -> None:
    """Walk the record stream so that gdstk never sees a file it would choke on."""
    if raw[:4] != b"\x00\x06\x00\x02":
        raise InputError(src, None, "not a GDSII file (it does not start with a HEADER record)")
    pos = 0
    element: tuple[int, set[int]] | None = None         # (its first byte, records still needed)
    while pos + 4 <= len(raw):
        length, rtype, dtype = int.from_bytes(raw[pos:pos + 2], "big"), raw[pos + 2], raw[pos + 3]
        size = _DATA_SIZE.get(dtype)
        if length < 4 or length % 2 or size is None or (size and (length - 4) % size) \
                or (size == 0 and length != 4):
            raise InputError(src, None, f"corrupt GDSII file (bad record at byte {pos})")
        if pos + length > len(raw):
            break
        if rtype == _ENDLIB:
            return
        if rtype in _ELEMENT_NEEDS:
            if element is not None:
                raise InputError(src, None, f"corrupt GDSII file (the element at byte {element[0]} has no "
                                            f"ENDEL before the next at byte {pos})")
            element = (pos, set(_ELEMENT_NEEDS[rtype]))
        elif rtype == _ENDEL:
            if element is None or element[1] or length != 4:
                where = f"the element at byte {element[0]}" if element else "nothing"
                raise InputError(src, None, f"corrupt GDSII file (the ENDEL at byte {pos} ends {where}"
                                            + (f", which lacks its {_names_of(element[1])}" if element and element[1]
                                               else "") + ")")
            element = None
        elif element is not None:
            element[1].discard(rtype)
        if rtype in (_STRNAME, _SNAME) and not _is_text(raw[pos + 4:pos + length]):
            raise InputError(src, None, f"corrupt GDSII file (the cell name at byte {pos} is not UTF-8 text)")
        pos += length
    raise InputError(src, None, "truncated GDSII file (it ends before the ENDLIB record)")


def _is_text(data: bytes) -> bool:
    """gdstk makes a cell name a Python string, and fails on what is not UTF-8."""
    try:
        data.rstrip(b"\0").decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def _names_of(records: set[int]) -> str:
    names = {_XY: "XY", _SNAME: "SNAME", _COLROW: "COLROW"}
    return " and ".join(names[r] for r in sorted(records)) + " record"


def _read(path: str | os.PathLike, src: str) -> tuple[gdstk.Library, Counter]:
    """The library, and what gdstk warned of while reading it (records it skipped,
    references to missing cells), counted for notes: never printed beside nanoasm's own
    lines."""
    try:
        with warnings.catch_warnings(record=True) as skipped, _c_stderr() as said:
            warnings.simplefilter("always")
            unit, precision = gdstk.gds_units(str(path))
            if not (math.isfinite(unit) and unit > 0 and math.isfinite(precision) and precision > 0):
                raise InputError(src, None, f"invalid library units ({unit!r} m, precision {precision!r} m)")
            lib = gdstk.read_gds(str(path), unit=1e-9)
    except (OSError, RuntimeError, ValueError) as exc:
        raise InputError(src, None, f"cannot read GDSII ({exc})") from None
    # gdstk tells twice: a Python warning, and a line of its own C code on stderr
    told = [str(w.message).rstrip(".") for w in skipped]
    told += [line.removeprefix("[GDSTK]").strip().rstrip(".") for line in said if line.startswith("[GDSTK]")]
    return lib, Counter(told)


@contextmanager
def _c_stderr() -> Iterator[list[str]]:
    """What C code writes to the process's stderr (file descriptor 2) meanwhile, as lines
    (filled on the way out) instead of on the user's terminal."""
    lines: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield lines
            finally:
                os.dup2(saved, 2)
                tmp.seek(0)
                lines.extend(tmp.read(1 << 16).decode("utf-8", "replace").splitlines())
    finally:
        os.close(saved)


def _top_cell(lib: gdstk.Library, name: str | None, src: str) -> gdstk.Cell:
    cells = {c.name: c for c in lib.cells}
    if not cells:
        raise InputError(src, None, "the library has no cells")
    if name is not None:
        if name not in cells:
            raise InputError(src, "--cell", f"no cell {name!r} (cells: {_names(cells)})")
        return cells[name]
    tops = lib.top_level()
    if len(tops) != 1:
        raise InputError(src, None, f"{len(tops)} top cells ({_names(c.name for c in tops)}); "
                                    "choose one with --cell")
    return tops[0]


@dataclass
class _Tally:
    """What flattening one cell would give (every count already multiplied out)."""
    instances: int = 1                                      # itself, its shapes, labels, placements
    vertices: int = 0                                       # of shapes on the role layers
    height: int = 0                                         # deepest reference chain below it
    shapes: Counter = field(default_factory=Counter)        # (layer, datatype) -> count
    labels: int = 0


class _Hierarchy:
    """Walks the reference hierarchy with gdstk's cell and reference objects (nothing is
    flattened): refuses a cycle, nesting past :data:`MAX_DEPTH` and flattened totals
    past :data:`MAX_INSTANCES` / :data:`MAX_VERTICES`. Each cell is counted once."""

    def __init__(self, src: str, role_layers: set[Layer]):
        self.src = src
        self.roles = role_layers
        self.done: dict[int, _Tally] = {}
        self.path: list[gdstk.Cell] = []

    def fail(self, cell: gdstk.Cell, problem: str) -> NoReturn:
        raise InputError(self.src, f"cell {cell.name}", problem)

    def tally(self, cell: gdstk.Cell) -> _Tally:
        known = self.done.get(id(cell))
        if known is None:
            if any(c is cell for c in self.path):
                chain = [c.name for c in self.path[[id(c) for c in self.path].index(id(cell)):]]
                self.fail(cell, f"references itself ({_chain([*chain, cell.name])}); "
                                "a cell must not contain itself")
            self.path.append(cell)
            if len(self.path) > MAX_DEPTH + 1:
                self.fail(self.path[0], f"references nested more than {MAX_DEPTH} deep "
                                        f"({_chain(c.name for c in self.path)})")
            known = self.done[id(cell)] = self._own(cell)
            self.path.pop()
        elif len(self.path) + known.height > MAX_DEPTH:
            self.fail(self.path[0], f"references nested more than {MAX_DEPTH} deep "
                                    f"({_chain([*(c.name for c in self.path), cell.name])} ...)")
        return known

    def _own(self, cell: gdstk.Cell) -> _Tally:
        t = _Tally(labels=sum(_copies(lb) for lb in cell.labels))
        t.instances += t.labels
        for poly in cell.polygons:
            n = _copies(poly)
            layer = (poly.layer, poly.datatype)
            t.shapes[layer] += n
            if layer in self.roles:
                t.vertices += n * poly.size
        for path in cell.paths:
            n = _copies(path)
            for i, layer in enumerate(zip(path.layers, path.datatypes)):
                t.shapes[layer] += n
                if layer in self.roles:
                    t.vertices += n * _path_vertices(path, i)
        t.instances += sum(t.shapes.values())
        self._check(cell, t)
        for ref in cell.references:
            if not isinstance(ref.cell, gdstk.Cell):    # a missing cell: gdstk draws nothing
                continue
            n = _copies(ref)
            sub = self.tally(ref.cell)
            t.instances += n * sub.instances
            t.vertices += n * sub.vertices
            t.height = max(t.height, sub.height + 1)
            t.labels += n * sub.labels
            for layer, k in sub.shapes.items():
                t.shapes[layer] += n * k
            self._check(cell, t, ref, n)
        return t

    def _check(self, cell: gdstk.Cell, t: _Tally, ref: gdstk.Reference | None = None,
               copies: int = 1) -> None:
        what = ""
        if ref is not None and copies > 1:
            rep = ref.repetition
            grid = f"{rep.columns} x {rep.rows}" if rep.columns else f"{copies} copies"
            what = f" (its array of {ref.cell.name}: {grid})"
        if t.instances > MAX_INSTANCES:
            self.fail(cell, f"flattening its references{what} would give more than the "
                            f"{MAX_INSTANCES} instances (shapes, labels and cell placements) "
                            "the importer allows")
        if t.vertices > MAX_VERTICES:
            self.fail(cell, f"flattening its references{what} would give more than the "
                            f"{MAX_VERTICES} vertices on the particle, rod, keep-out and area "
                            "layers the importer allows")


def _copies(element) -> int:
    """How many times a shape, label or reference is placed (its repetition's count)."""
    rep = element.repetition
    return max(1, int(rep.size)) if rep is not None else 1


def _path_vertices(path, i: int) -> int:
    """Vertices of the polygon gdstk draws for sub-path ``i`` (round ends as arcs drawn
    to the path's tolerance: a huge width means a huge number of points)."""
    n = 2 * len(path.spine())
    if path.ends[i] == "round":
        r = float(path.widths()[:, i].max()) / 2
        tol = float(path.tolerance)
        if not (math.isfinite(r) and tol > 0):
            return MAX_VERTICES + 1
        if r > tol:
            n += 2 * math.ceil(math.pi / (2 * math.acos(1 - tol / r)))
    return n


def _chain(names, limit: int = 6) -> str:
    names = list(names)
    if len(names) > limit:
        names = [*names[:3], "...", *names[-2:]]
    return " > ".join(names)


def _names(names, limit: int = 8) -> str:
    names = sorted(names)
    more = f", ... ({len(names)} in all)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


# -- shapes -------------------------------------------------------------------------

def _key(kind: str, layer: Layer, points: np.ndarray) -> str:
    x, y = np.mean(points, axis=0)
    return f"{kind} on layer {layer[0]}/{layer[1]} at ({x:.6g}, {y:.6g}) nm"


def _shift(p, origin: Point) -> Point:
    return float(p[0]) - origin[0], float(p[1]) - origin[1]


def _working_area(top: gdstk.Cell, layer: Layer, size: Point | None,
                  b: LayoutBuilder) -> tuple[Point, Point]:
    """``(origin, (width, height))`` in nm."""
    polys = top.get_polygons(include_paths=True, layer=layer[0], datatype=layer[1])
    where = f"layer {layer[0]}/{layer[1]}"
    if len(polys) > 1:
        b.fail(where, f"{len(polys)} shapes on the working-area layer; expected one rectangle")
    if not polys:
        if size is None:
            b.fail(None, f"no working area: draw one rectangle on layer {layer[0]}/{layer[1]} "
                         "or give --area W H")
        return (0.0, 0.0), size
    if size is not None:
        b.fail("--area", f"the file already has a working-area rectangle on {where}; drop --area")
    rect = axis_rectangle(polys[0].points)
    if rect is None:
        b.fail(_key("polygon", layer, polys[0].points), "the working area must be an axis-aligned rectangle")
    x0, y0, w, h = rect
    return (x0, y0), (w, h)


def _particles(top: gdstk.Cell, layer: Layer, origin: Point, b: LayoutBuilder) -> None:
    polys = top.get_polygons(include_paths=True, layer=layer[0], datatype=layer[1])
    if len(polys) > 1:  # writers split polygons of many vertices (gdstk: over 199); rejoin
        polys = gdstk.boolean(polys, [], "or", precision=1e-3)
    for poly in polys:
        key = _key("polygon", layer, poly.points)
        pts = np.array(ring(poly.points))
        if len(pts) < MIN_CORNERS:
            b.fail(key, f"has {len(pts)} corners; a particle must be a circle polygon "
                        f"(at least {MIN_CORNERS} vertices)")
        centre, radius, deviation, gap = fit_circle(pts)
        if deviation > ROUND_TOL or gap > MAX_GAP_DEG:
            b.fail(key, f"is not round (its vertices stray up to {deviation:.0%} from a circle, "
                        f"largest gap {gap:.0f} deg); a particle must be a circle polygon")
        b.particle(key, _shift(centre, origin), 2 * radius)


def fit_circle(points: np.ndarray) -> tuple[Point, float, float, float]:
    """Least-squares circle through ``(N, 2)`` vertices.

    Returns
    -------
    centre, radius, deviation, gap
        Largest relative distance of a vertex from the circle, and the largest angle
        (degrees) between angularly neighbouring vertices seen from the centre.
    """
    mean = points.mean(axis=0)
    q = points - mean
    a = np.column_stack([2 * q, np.ones(len(q))])
    (cx, cy, c), *_ = np.linalg.lstsq(a, (q ** 2).sum(axis=1), rcond=None)
    radius = math.sqrt(max(c + cx * cx + cy * cy, 0.0))
    d = q - (cx, cy)
    rho = np.hypot(d[:, 0], d[:, 1])
    deviation = float(np.max(np.abs(rho - radius)) / radius) if radius > 0 else math.inf
    angles = np.sort(np.arctan2(d[:, 1], d[:, 0]))
    gaps = np.diff(np.concatenate([angles, angles[:1] + 2 * math.pi]))
    centre = (float(mean[0] + cx), float(mean[1] + cy))
    return centre, radius, deviation, float(np.degrees(gaps.max()))


def _rods(top: gdstk.Cell, layer: Layer, origin: Point, b: LayoutBuilder) -> None:
    for path in top.get_paths(layer=layer[0], datatype=layer[1]):
        spine = path.spine()
        for i in range(path.num_paths):
            if (path.layers[i], path.datatypes[i]) == layer:
                _path_rod(spine, path.widths()[:, i], path.ends[i], layer, origin, b)
    for poly in top.get_polygons(include_paths=False, layer=layer[0], datatype=layer[1]):
        _rectangle_rod(poly.points, layer, origin, b)


def _path_rod(spine: np.ndarray, widths: np.ndarray, ends, layer: Layer, origin: Point,
              b: LayoutBuilder) -> None:
    key = _key("path", layer, spine)
    w = float(widths.max())  # a GDSII PATH has one width
    if not w > 0:
        b.fail(key, "path has no width (the width is the rod diameter)")
    start, end = spine[0], spine[-1]
    axis = end - start
    length = float(np.hypot(*axis))
    if length == 0:
        b.fail(key, "path has zero length")
    rel = spine - start
    along = rel @ axis / length
    across = np.abs(rel[:, 0] * axis[1] - rel[:, 1] * axis[0]) / length
    if across.max() > 0.01 * w or np.any(np.diff(along) < 0):
        b.fail(key, "path bends; a rod path must be straight")
    if ends == "flush":
        extension = 0.0
    elif ends in ("round", "extended"):
        extension = w
    elif isinstance(ends, tuple) and len(ends) == 2:
        extension = float(ends[0]) + float(ends[1])
    else:
        b.fail(key, f"unsupported path ends {ends!r}")
    b.rod(key, _shift(start, origin), _shift(end, origin), w, extension)


def _rectangle_rod(points: np.ndarray, layer: Layer, origin: Point, b: LayoutBuilder) -> None:
    key = _key("polygon", layer, points)
    corners = np.array(ring(points))
    if len(corners) != 4:
        b.fail(key, f"has {len(corners)} corners; a rod polygon must be a rectangle "
                    "(or draw the rod as a path)")
    edges = np.roll(corners, -1, axis=0) - corners
    lengths = np.hypot(edges[:, 0], edges[:, 1])
    cosines = [abs(edges[k] @ edges[k - 1]) / (lengths[k] * lengths[k - 1]) for k in range(4)]
    sides = ((lengths[0] + lengths[2]) / 2, (lengths[1] + lengths[3]) / 2)
    if max(cosines) > RECT_TOL or abs(lengths[0] - lengths[2]) > RECT_TOL * min(sides) \
            or abs(lengths[1] - lengths[3]) > RECT_TOL * min(sides):
        b.fail(key, "is not a rectangle; a rod polygon must be a rectangle (or draw the rod as a path)")
    if abs(sides[0] - sides[1]) <= 1e-9 * max(sides):
        b.fail(key, "is a square; a rod rectangle needs a long side (its axis)")
    k = 0 if sides[0] > sides[1] else 1
    length, diameter = sides[k], sides[1 - k]
    axis = (edges[k] - edges[k + 2]) / 2
    unit = axis / np.hypot(*axis)
    centre = corners.mean(axis=0)
    half = unit * length / 2
    b.rod(key, _shift(centre - half, origin), _shift(centre + half, origin), diameter)


def _count_ignored(tally: _Tally, used: set[Layer], b: LayoutBuilder) -> None:
    for (layer, datatype), n in sorted(tally.shapes.items()):
        if (layer, datatype) not in used and n:
            b.ignore(f"shape(s) on layer {layer}/{datatype}", n)
    if tally.labels:
        b.ignore("text label(s)", tally.labels)
