"""SVG importer: ``<circle>`` -> particle slot, ``<line>`` -> rod slot, keep-out shapes.

Mapping (user units are the root viewBox's, times ``scale`` nm):

- ``<circle>``: particle at its centre, diameter ``2 r``.
- ``<line>``: rod between its end points, diameter = ``stroke-width`` (required; set on
  the line, a parent group, its style or a CSS rule). The length is the line's; with
  ``stroke-linecap`` round or square the drawn caps add one stroke-width.
- Keep-outs: closed shapes (rect, polygon, circle, ellipse, closed polyline or path;
  curves flattened) inside a ``<g>`` whose class is ``keepout_class``, whose id or
  Inkscape layer label starts with it, or carrying that class themselves. Every closed
  sub-path of a path is one polygon.
- Alignment marks (``marks_layer``, none by default): closed shapes marked by that
  class or group name the same way; they are keep-outs too.
- Working area: the root viewBox (else its width and height); y is flipped, so the
  viewBox's lower-left corner is the origin.

Transforms (also ``<use>``) are applied. Element ids become target ids. The XML is
checked with defusedxml first: entity declarations and external references are
refused before svgelements sees the file. Then, still before svgelements, the tree is
walked with ``<use>`` references followed as svgelements will (issue 15: 100k nested
``<g>`` and ``<use>`` cycles raised RecursionError, a 3.9 KB ``<use>`` fan-out ran for
minutes): a ``<use>`` cycle, nesting past :data:`MAX_DEPTH` and more than
:data:`MAX_INSTANCES` elements after expansion are refused with one line.
"""

from __future__ import annotations

import io
import math
import os
import re
from collections import Counter
from pathlib import Path
from typing import NoReturn
from xml.etree.ElementTree import Element, ParseError, tostring

import defusedxml
import defusedxml.ElementTree as safe_et
import svgelements as S

from nanoasm.errors import InputError

from nanoasm.fileio import read_bytes

from .importers import FLATTEN_NM, LayoutBuilder, Point, name_option, positive_option

SVG_NS = "{http://www.w3.org/2000/svg}"
#: Attributes added before svgelements parses the file: an element's name in errors,
#: and a mark on content that is drawn only through ``<use>`` or not at all.
KEY_ATTR = "data-nanoasm-key"
UNDRAWN_ATTR = "data-nanoasm-undrawn"
UNDRAWN = {"defs", "symbol", "clipPath", "mask", "marker", "pattern", "linearGradient",
           "radialGradient", "filter", "metadata", "foreignObject", "title", "desc"}
INKSCAPE_LABEL = "{http://www.inkscape.org/namespaces/inkscape}label"
KEEPOUT_TAGS = ("rect", "polygon", "polyline", "path", "circle", "ellipse")

#: Deepest nesting of elements, a ``<use>`` counting one level above what it draws.
#: Drawings nest a few groups (Inkscape layers and groups, ~10); ElementTree's writer
#: and svgelements recurse once per level, so 100 000 nested ``<g>`` hit Python's
#: recursion limit (RecursionError). 128 stays far below it.
MAX_DEPTH = 128
#: Most elements svgelements may build: every element of the file plus every copy a
#: ``<use>`` makes of its target (nested ``<use>`` multiply). svgelements builds ~25 000
#: elements a second here (50 000: ~2 s, ~200 MB, and real drawings have a few
#: thousand); the 3.9 KB fan-out of issue 15 asks for 10^11.
MAX_INSTANCES = 50_000

#: User units per unit (CSS: 96 px per inch).
UNITS = {"": 1.0, "px": 1.0, "in": 96.0, "cm": 96 / 2.54, "mm": 96 / 25.4, "pt": 96 / 72, "pc": 16.0}
_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_LENGTH = re.compile(rf"\s*({_NUMBER})\s*([A-Za-z%]*)\s*")
_SEPARATOR = re.compile(r"\s*,\s*|\s+")


def import_svg(path: str | os.PathLike, *, scale: float = 1.0, keepout_class: str = "keepout",
               marks_layer: str | None = None, warnings: list[str] | None = None) -> dict:
    """Read an SVG drawing as a layout v1 dict.

    Parameters
    ----------
    path : str or path-like
        The SVG file.
    scale : float
        Nanometres per SVG user unit.
    keepout_class : str
        Class (or id / layer-label prefix of a group) that marks keep-out shapes.
    marks_layer : str, optional
        The same for alignment marks (closed shapes, as keep-outs); none by default.
    warnings : list of str, optional
        Receives a line per kind of ignored element.
    """
    src = str(path)
    scale = positive_option("scale", scale)
    keepout_class = name_option("keepout_class", keepout_class)
    marks_layer = None if marks_layer is None else name_option("marks_layer", marks_layer)
    raw = read_bytes(path)
    root = _safe_root(raw, src)
    vx, vy, width, height = _viewport(root, src)
    doc = _parse(_annotate(root, src), src)
    builder = LayoutBuilder(src, Path(path).stem)
    builder.units = f"--scale {scale:g} nm per user unit"
    frame = _Frame(vx, vy + height, scale)
    _Walker(builder, frame, _to_user(doc, src), keepout_class, marks_layer).run(doc)
    layout = builder.build((width * scale, height * scale),
                           "expected <circle> elements for particles or <line> elements for rods")
    builder.report(warnings)
    return layout


# -- reading ------------------------------------------------------------------------

def _safe_root(raw: bytes, src: str) -> Element:
    """Parse with defusedxml (no entities, no external references); return the root."""
    if b"\x00" in raw and not raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise InputError(src, None, "binary file, expected SVG text")
    try:
        root = safe_et.fromstring(raw, forbid_dtd=False, forbid_entities=True, forbid_external=True)
    except defusedxml.EntitiesForbidden:
        raise InputError(src, None, "XML entity declarations are not allowed (unsafe)") from None
    except defusedxml.DefusedXmlException as exc:
        raise InputError(src, None, f"unsafe XML refused: {exc}") from None
    except ParseError as exc:
        what = "truncated XML" if exc.code == 3 else "not valid XML"  # 3: no element found
        raise InputError(src, None, f"{what}: {exc}") from None
    if _local(root.tag) != "svg":
        raise InputError(src, None, f"not an SVG file (the root element is <{root.tag}>)")
    return root


def _local(tag) -> str | None:
    """The SVG element name of ``tag`` (``None`` for other namespaces and comments)."""
    if not isinstance(tag, str):
        return None
    if tag.startswith(SVG_NS):
        return tag[len(SVG_NS):]
    return None if tag.startswith("{") else tag


#: Length attributes checked strictly (svgelements drops elements with bad values).
_LENGTHS = {"circle": ("cx", "cy", "r"), "line": ("x1", "y1", "x2", "y2"),
            "rect": ("x", "y", "width", "height", "rx", "ry"), "ellipse": ("cx", "cy", "rx", "ry")}


def _annotate(root: Element, src: str) -> bytes:
    """Check geometry attributes, name every element for error lines, mark undrawn
    content (in ``<defs>``, ``<mask>``, ...) and serialize.

    Elements are named ``tag#id``, else ``tag[n]`` (the n-th such element in the file).
    """
    count: Counter[str] = Counter()
    stack = [(root, False)]
    while stack:
        el, undrawn = stack.pop()
        tag = _local(el.tag)
        if tag is None:
            continue
        stack.extend((kid, undrawn or tag in UNDRAWN) for kid in reversed(el))
        if undrawn:
            el.set(UNDRAWN_ATTR, "1")
        count[tag] += 1
        key = f"{tag}#{el.get('id')}" if el.get("id") else f"{tag}[{count[tag]}]"
        for name in _LENGTHS.get(tag, ()):
            if el.get(name, "auto").strip() != "auto":
                _length(el.attrib, name, key, src)
        if tag == "circle":
            r = _length(el.attrib, "r", key, src)
            if r <= 0:
                raise InputError(src, key, f"r must be positive, got {r:g}")
        if tag in ("polygon", "polyline"):
            _check_points(el.get("points", ""), key, src)
        el.set(KEY_ATTR, key)
    _Expansion(root, src).check()
    return tostring(root, encoding="utf-8")


class _Expansion:
    """Counts the elements svgelements will build, following ``<use>`` as it does
    (``href`` over ``xlink:href``, the id after the first character, the last element of
    an id): refuses a cycle, nesting past :data:`MAX_DEPTH` and more than
    :data:`MAX_INSTANCES` elements. Each element is counted once."""

    def __init__(self, root: Element, src: str):
        self.root = root
        self.src = src
        self.ids = {el.get("id"): el for el in root.iter() if el.get("id") is not None}
        self.done: dict[int, tuple[int, int]] = {}          # id(element) -> (elements, height)
        self.path: list[Element] = []

    def check(self) -> None:
        self._visit(self.root)

    def fail(self, el: Element, problem: str) -> NoReturn:
        raise InputError(self.src, _key(el), problem)

    def _visit(self, el: Element) -> tuple[int, int]:
        known = self.done.get(id(el))
        if known is not None:
            if len(self.path) + known[1] >= MAX_DEPTH:
                self._too_deep(el)
            return known
        if any(p is el for p in self.path):
            use = self.path[-1]
            self.fail(use, "<use> refers to itself" if use is el else
                      f"<use> refers to {_key(el)}, which leads back to this <use> (a reference cycle)")
        self.path.append(el)
        if len(self.path) > MAX_DEPTH:
            self._too_deep(el)
        parts = list(el)
        if _use_tag(el.tag):
            href = el.get(XLINK_HREF)
            href = el.get("href", href)
            target = self.ids.get(href[1:]) if href is not None else None
            if target is not None:
                parts.append(target)
        count, height = 1, 0
        for part in parts:
            n, h = self._visit(part)
            count, height = count + n, max(height, h + 1)
            if count > MAX_INSTANCES:
                self.fail(el, f"expands to more than the {MAX_INSTANCES} elements the importer "
                              "allows (each copy a <use> makes counted)")
        self.path.pop()
        self.done[id(el)] = (count, height)
        return count, height

    def _too_deep(self, el: Element) -> NoReturn:
        self.fail(el, f"elements are nested more than {MAX_DEPTH} deep (a <use> counts as a "
                      "level above what it draws)")


XLINK_HREF = "{http://www.w3.org/1999/xlink}href"


def _use_tag(tag) -> bool:
    """Whether svgelements expands the element (``use``, SVG or no namespace)."""
    return isinstance(tag, str) and (tag == "use" or (tag.startswith("{http://www.w3.org/2000/svg")
                                                       and tag[28:] == "use"))


def _key(el: Element) -> str:
    return str(el.get(KEY_ATTR) or _local(el.tag) or el.tag)


def _parse(raw: bytes, src: str) -> S.SVG:
    try:
        return S.SVG.parse(io.BytesIO(raw), reify=False)
    except Exception as exc:  # svgelements raises assorted errors on bad attribute values
        raise InputError(src, None, f"cannot interpret the SVG ({type(exc).__name__}: {exc})") from None


def _viewport(root: Element, src: str) -> tuple[float, float, float, float]:
    """``(min_x, min_y, width, height)`` of the working area in user units."""
    box = root.get("viewBox")
    if box is not None:
        try:
            nums = [float(v) for v in _SEPARATOR.split(box.strip())]
        except ValueError:
            nums = []
        if len(nums) != 4 or not all(math.isfinite(v) for v in nums):
            raise InputError(src, "svg", "viewBox must be four numbers 'min-x min-y width height', "
                                         f"got {box!r}")
        if nums[2] <= 0 or nums[3] <= 0:
            raise InputError(src, "svg", f"viewBox width and height must be positive, got {box!r}")
        return nums[0], nums[1], nums[2], nums[3]
    if root.get("width") is None or root.get("height") is None:
        raise InputError(src, "svg", "no working area: the root <svg> has neither a viewBox "
                                     "nor a width and a height")
    for name in ("width", "height"):
        if root.get(name, "").strip().endswith("%"):
            raise InputError(src, "svg", f"{name} is a percentage; give the root <svg> a viewBox")
    w = _length(root.attrib, "width", "svg", src)
    h = _length(root.attrib, "height", "svg", src)
    if w <= 0 or h <= 0:
        raise InputError(src, "svg", f"width and height must be positive, got {w:g} x {h:g}")
    return 0.0, 0.0, w, h


def _length(attrs: dict, name: str, key: str, src: str, default: float | None = None) -> float:
    """An SVG length attribute in user units; absolute units only."""
    raw = attrs.get(name)
    if raw is None:
        if default is None:
            raise InputError(src, key, f"{name} is missing")
        return default
    m = _LENGTH.fullmatch(str(raw))
    if m is None:
        raise InputError(src, key, f"{name} is not a length: {str(raw)[:40]!r}")
    unit = m[2].lower()
    if unit not in UNITS:
        raise InputError(src, key, f"{name} uses the unit {m[2]!r}; use user units or "
                                   "px, mm, cm, in, pt, pc")
    value = float(m[1]) * UNITS[unit]
    if not math.isfinite(value):
        raise InputError(src, key, f"{name} is not finite: {raw!r}")
    return value


def _to_user(doc: S.SVG, src: str) -> S.Matrix:
    """The inverse of the root's viewBox-to-viewport transform: back to user units."""
    root = S.Matrix(doc.viewbox_transform) if doc.viewbox_transform else S.Matrix()
    det = root.determinant
    if not math.isfinite(det) or det == 0:
        raise InputError(src, "svg", "the root <svg> has a zero or invalid width or height")
    return ~root


# -- mapping ------------------------------------------------------------------------

class _Frame:
    """User units -> layout nm: shift to the viewBox's lower-left corner, flip y."""

    def __init__(self, x0: float, top: float, scale: float):
        self.x0, self.top, self.scale = x0, top, scale

    def __call__(self, p: Point) -> Point:
        return (p[0] - self.x0) * self.scale, (self.top - p[1]) * self.scale


class _Walker:
    """Walks the parsed tree in document order and feeds the builder."""

    def __init__(self, builder: LayoutBuilder, frame: _Frame, to_user: S.Matrix, keepout_class: str,
                 marks_class: str | None = None):
        self.b = builder
        self.frame = frame
        self.to_user = to_user
        self.mark = keepout_class
        self.marks = marks_class

    def run(self, doc: S.SVG) -> None:
        # (element, inside a keep-out group, inside a <use>, id given by that <use>)
        stack: list[tuple] = [(e, False, False, None) for e in reversed(list(doc))]
        while stack:
            e, keepout, in_use, use_id = stack.pop()
            attrs = e.values.get("attributes", {}) if hasattr(e, "values") else {}
            if attrs.get(UNDRAWN_ATTR) and not in_use:
                continue
            if isinstance(e, (S.Shape, S.Text, S.Image)) and _hidden(e):
                self.b.ignore("hidden element(s)")
                continue
            if isinstance(e, S.Use):
                kids = list(e)
                uid = attrs.get("id") if _count_shapes(kids) == 1 else None
                inner = keepout or self._marked(attrs)
                stack.extend((k, inner, True, uid) for k in reversed(kids))
            elif isinstance(e, S.Group):
                inner = keepout or self._marked(attrs, group=True)
                stack.extend((k, inner, in_use, use_id) for k in reversed(list(e)))
            elif isinstance(e, S.Shape):
                self._shape(e, attrs, keepout or self._marked(attrs), use_id if in_use else attrs.get("id"))
            elif isinstance(e, (S.Text, S.Image)):
                self.b.ignore(f"<{attrs.get('tag', type(e).__name__.lower())}>")

    def _marked(self, attrs: dict, group: bool = False) -> str | bool:
        """The role the element's class (or a group's id or layer label) gives what it
        holds: ``"mark"`` (an alignment mark), True (a keep-out) or False."""
        names = (str(attrs.get("id", "")), str(attrs.get(INKSCAPE_LABEL, ""))) if group else ()
        for role, cls in (("mark", self.marks), (True, self.mark)):
            if cls is None:
                continue
            if cls in str(attrs.get("class", "")).split() or any(n.lower().startswith(cls.lower()) for n in names):
                return role
        return False

    def _shape(self, e: S.Shape, attrs: dict, keepout: bool, target_id: str | None) -> None:
        tag = str(attrs.get("tag") or type(e).__name__.lower())
        key = str(attrs.get(KEY_ATTR, tag))
        m = S.Matrix(e.transform) * self.to_user
        if not all(math.isfinite(v) for v in (m.a, m.b, m.c, m.d, m.e, m.f)):
            self.b.fail(key, "transform is not finite")
        if keepout:
            self._keepout(e, tag, key, m, "mark" if keepout == "mark" else "keep-out")
        elif tag == "circle":
            self._particle(attrs, key, m, target_id or None)
        elif tag == "line":
            self._rod(e, attrs, key, m, target_id or None)
        else:
            self.b.ignore(f"<{tag}>")

    def _particle(self, attrs: dict, key: str, m: S.Matrix, target_id: str | None) -> None:
        src = self.b.source
        cx, cy = _length(attrs, "cx", key, src, 0.0), _length(attrs, "cy", key, src, 0.0)
        r = _length(attrs, "r", key, src)
        if not _similarity(m):
            self.b.fail(key, "its transform stretches or skews the circle (only rotation, "
                             "uniform scaling and translation keep it a circle)")
        c = m.point_in_matrix_space((cx, cy))
        diameter = 2 * r * math.sqrt(abs(m.determinant)) * self.frame.scale
        self.b.particle(key, self.frame((c.x, c.y)), diameter, target_id)

    def _rod(self, e: S.Shape, attrs: dict, key: str, m: S.Matrix, target_id: str | None) -> None:
        src = self.b.source
        x1, y1 = _length(attrs, "x1", key, src, 0.0), _length(attrs, "y1", key, src, 0.0)
        x2, y2 = _length(attrs, "x2", key, src, 0.0), _length(attrs, "y2", key, src, 0.0)
        if e.values.get("stroke-width") is None:
            self.b.fail(key, "stroke-width is missing (it sets the rod diameter)")
        width = _length(e.values, "stroke-width", key, src)
        if width <= 0:
            self.b.fail(key, f"stroke-width must be positive, got {width:g}")
        ux, uy = x2 - x1, y2 - y1
        if math.hypot(ux, uy) == 0:
            self.b.fail(key, "line has zero length")
        # A stroke's width across the line scales by |det| / (stretch along the line).
        along = math.hypot(m.a * ux + m.c * uy, m.b * ux + m.d * uy) / math.hypot(ux, uy)
        diameter = width * abs(m.determinant) / along * self.frame.scale
        cap = str(e.values.get("stroke-linecap", "butt")).strip()
        extension = diameter if cap in ("round", "square") else 0.0
        p, q = m.point_in_matrix_space((x1, y1)), m.point_in_matrix_space((x2, y2))
        self.b.rod(key, self.frame((p.x, p.y)), self.frame((q.x, q.y)), diameter, extension, target_id)

    def _keepout(self, e: S.Shape, tag: str, key: str, m: S.Matrix, what: str = "keep-out") -> None:
        if tag == "line":
            self.b.fail(key, f"a <line> cannot be a {what} (it encloses no area); use a closed shape")
        if tag not in KEEPOUT_TAGS:
            self.b.ignore(f"<{tag}> in a {what} group")
            return
        try:
            path = S.Path(e)
            path.transform = S.Matrix(m)
            path = abs(path)
        except Exception as exc:  # svgelements on a degenerate shape
            self.b.fail(key, f"cannot read the outline ({type(exc).__name__}: {exc})")
        outlines = _outlines(path, FLATTEN_NM / self.frame.scale)
        if not outlines:
            self.b.fail(key, f"{what} shape has no outline")
        for points, closed in outlines:
            if not closed:
                self.b.fail(key, f"{what} outline is not closed (end the path with Z)")
            self.b.keepout(key, [self.frame(p) for p in points], what=what)


def _count_shapes(elements: list) -> int:
    """Shapes in ``elements`` and their groups: a ``<use>`` of one shape lends it its id."""
    n, stack = 0, list(elements)
    while stack:
        e = stack.pop()
        if isinstance(e, S.Shape):
            n += 1
        elif isinstance(e, (S.Group, S.Use)):
            stack.extend(e)
    return n


def _hidden(e: S.SVGElement) -> bool:
    """``visibility: hidden`` (inherited); svgelements already drops ``display: none``."""
    return str(e.values.get("visibility", "")).strip() in ("hidden", "collapse")


def _similarity(m: S.Matrix) -> bool:
    """Whether ``m`` maps circles to circles (rotation, reflection, uniform scale)."""
    n1, n2 = math.hypot(m.a, m.b), math.hypot(m.c, m.d)
    tol = 1e-9 * max(n1, n2)
    return abs(n1 - n2) <= tol and abs(m.a * m.c + m.b * m.d) <= tol * max(n1, n2) and n1 > 0


def _check_points(raw: str, key: str, src: str) -> None:
    tokens = [t for t in _SEPARATOR.split(str(raw).strip()) if t]
    if len(tokens) % 2 or not all(re.fullmatch(_NUMBER, t) for t in tokens):
        raise InputError(src, key, f"points must be pairs of numbers, got {str(raw)[:40]!r}")
    if not all(math.isfinite(float(t)) for t in tokens):
        raise InputError(src, key, "points are not finite")


def _outlines(path: S.Path, tol: float) -> list[tuple[list[Point], bool]]:
    """Sub-paths as vertex lists (curves flattened to within ``tol``) and closed flags."""
    out: list[tuple[list[Point], bool]] = []
    cur: list[Point] = []
    for seg in path:
        if isinstance(seg, S.Move):
            if len(cur) > 1:
                out.append((cur, _same(cur[0], cur[-1], tol)))
            cur = [_xy(seg.end)]
        elif isinstance(seg, S.Close):
            if len(cur) > 1:
                out.append((cur, True))
            cur = []
        else:
            if not cur:
                cur = [_xy(seg.start)]
            if isinstance(seg, S.Line):
                cur.append(_xy(seg.end))
            else:
                _flatten(seg, cur, tol)
    if len(cur) > 1:
        out.append((cur, _same(cur[0], cur[-1], tol)))
    return out


def _flatten(seg: S.PathSegment, out: list[Point], tol: float, max_depth: int = 10) -> None:
    """Append points along a curve until every chord is within ``tol`` of it."""
    def split(t0: float, p0: Point, t1: float, p1: Point, depth: int) -> None:
        tm = (t0 + t1) / 2
        pm = _xy(seg.point(tm))
        if depth >= max_depth or (depth >= 3 and _chord_gap(p0, pm, p1) <= tol):
            out.append(p1)
            return
        split(t0, p0, tm, pm, depth + 1)
        split(tm, pm, t1, p1, depth + 1)

    split(0.0, _xy(seg.start), 1.0, _xy(seg.end), 0)


def _chord_gap(a: Point, p: Point, b: Point) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    n = math.hypot(dx, dy)
    if n == 0:
        return math.hypot(p[0] - a[0], p[1] - a[1])
    return abs(dx * (p[1] - a[1]) - dy * (p[0] - a[0])) / n


def _same(a: Point, b: Point, tol: float) -> bool:
    return math.hypot(a[0] - b[0], a[1] - b[1]) <= tol * 1e-3


def _xy(p) -> Point:
    return float(p[0]), float(p[1])
