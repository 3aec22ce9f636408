"""Import target layouts from CAD files: SVG, GDSII and DXF.

Each importer maps CAD entities to the plain dict a parsed ``nanoasm.layout/1`` file
has (nanometres, degrees counter-clockwise from +x, rod angles in [0, 180), origin at
the lower-left corner of the working area, y up); :func:`nanoasm.cad.layout.layout_from_dict`
validates it. A file an importer cannot interpret raises
:class:`~nanoasm.errors.InputError` with one line naming the file, the element and
the problem::

    layout = import_layout("chip.svg", scale=2.0)          # dict, not yet validated

:class:`LayoutBuilder` collects slots, keep-outs and alignment marks (``marks_layer``:
an SVG class or group name, a GDSII ``L/D``, a DXF layer) for the format modules
(:mod:`.svg`, :mod:`.gds`, :mod:`.dxf`), which are imported only when needed.
"""

from __future__ import annotations

import importlib
import math
import os
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from nanoasm.errors import InputError
from nanoasm.param import check_number

FORMAT = "nanoasm.layout/1"

#: A working area's side (nm) beyond which the drawing's units are taken to be wrong
#: (1 mm, more than any AFM scanner's range): the import is refused with a hint.
IMPLAUSIBLE_SIDE = 1e6

#: Largest distance (nm) between a flattened curve and its chords.
FLATTEN_NM = 1.0

#: Most targets plus keep-outs one import may produce. Each costs ~0.1-0.2 ms to map
#: and validate, so 20 000 stay within a few seconds; an AFM places targets one push at a
#: time, and real layouts have tens to thousands. Past it the import stops with one
#: line instead of running for minutes (issue 15). The format modules budget their own
#: expansion (``MAX_DEPTH``, ``MAX_INSTANCES``, ...) before any of it is built.
MAX_ELEMENTS = 20_000

#: File suffix -> format module.
SUFFIXES = {".svg": "svg", ".gds": "gds", ".gds2": "gds", ".gdsii": "gds", ".dxf": "dxf"}

#: Keyword options each format accepts (besides ``warnings``).
OPTIONS = {
    "svg": ("scale", "keepout_class", "marks_layer"),
    "gds": ("cell", "area", "particle_layer", "rod_layer", "keepout_layer", "area_layer", "marks_layer"),
    "dxf": ("scale", "rod_diameter", "area", "marks_layer"),
}

Point = tuple[float, float]


def import_layout(path: str | os.PathLike, *, warnings: list[str] | None = None,
                  **options: Any) -> dict:
    """Import a CAD layout, choosing the importer by the file's suffix.

    Parameters
    ----------
    path : str or path-like
        ``.svg``, ``.gds`` (``.gds2``, ``.gdsii``) or ``.dxf`` file.
    warnings : list of str, optional
        Receives one line per kind of element that was ignored.
    **options
        Format options (see :data:`OPTIONS`); an option set to ``None`` counts as not
        given, so a CLI can pass all of its options through.

    Returns
    -------
    dict
        The layout v1 document, ready for ``layout_from_dict``.
    """
    src = str(path)
    fmt = SUFFIXES.get(Path(path).suffix.lower())
    if fmt is None:
        known = ", ".join(sorted(SUFFIXES))
        raise InputError(src, None, f"unknown layout file type {Path(path).suffix or '(none)'!r}; "
                                    f"expected one of {known}")
    given = {k: v for k, v in options.items() if v is not None}
    for name in given:
        if name not in OPTIONS[fmt]:
            allowed = ", ".join(flag(o) for o in OPTIONS[fmt])
            raise InputError(src, flag(name), f"does not apply to {fmt.upper()} files "
                                              f"(options for {fmt.upper()}: {allowed})")
    module = importlib.import_module(f"nanoasm.cad.{fmt}")
    return getattr(module, f"import_{fmt}")(path, warnings=warnings, **given)


# -- options ------------------------------------------------------------------------

def flag(name: str) -> str:
    """The command-line spelling of an option: ``rod_diameter`` -> ``--rod-diameter``."""
    return "--" + name.replace("_", "-")


def positive_option(name: str, value: Any) -> float:
    """A positive, finite number option (``scale``, ``rod_diameter``)."""
    def fail(problem: str) -> NoReturn:
        raise InputError(None, flag(name), problem)

    return check_number(value, fail, positive=True)


def area_option(value: Any) -> Point:
    """The ``area`` option: width and height in nm."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2:
        raise InputError(None, "--area", f"must be two numbers W H, got {value!r}")
    w, h = (positive_option("area", v) for v in value)
    return w, h


def layer_option(name: str, value: Any) -> tuple[int, int]:
    """A GDSII ``(layer, datatype)`` option; the string ``"L/D"`` is accepted too."""
    if isinstance(value, str):
        parts = value.split("/")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise InputError(None, flag(name), f"must be LAYER/DATATYPE such as 1/0, got {value!r}")
        value = (int(parts[0]), int(parts[1]))
    if (not isinstance(value, Sequence) or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
        raise InputError(None, flag(name), f"must be two integers LAYER/DATATYPE, got {value!r}")
    if min(value) < 0:
        raise InputError(None, flag(name), f"must not be negative, got {value[0]}/{value[1]}")
    return int(value[0]), int(value[1])


def name_option(name: str, value: Any) -> str:
    """A non-empty name without white space (``cell``, ``keepout_class``)."""
    if not isinstance(value, str) or not value.strip():
        raise InputError(None, flag(name), f"must be a non-empty name, got {value!r}")
    return value.strip()


# -- files --------------------------------------------------------------------------

# -- geometry -----------------------------------------------------------------------

def ring(points: Iterable[Sequence[float]], collinear: float = 1e-9) -> list[Point]:
    """A polygon's distinct corners: repeats, a closing repeat and straight-through
    vertices (relative cross product at most ``collinear``) are dropped."""
    out: list[Point] = []
    for p in points:
        q = (float(p[0]), float(p[1]))
        if out and q == out[-1]:
            continue
        while len(out) >= 2 and _straight(out[-2], out[-1], q, collinear):
            out.pop()
        out.append(q)
    while len(out) > 1 and out[0] == out[-1]:
        out.pop()
    while len(out) > 3 and _straight(out[-2], out[-1], out[0], collinear):
        out.pop()
    while len(out) > 3 and _straight(out[-1], out[0], out[1], collinear):
        out.pop(0)
    return out


def _straight(a: Point, b: Point, c: Point, tol: float) -> bool:
    """Whether ``b`` lies on the way from ``a`` to ``c`` (no turn, no reversal)."""
    u, v = (b[0] - a[0], b[1] - a[1]), (c[0] - b[0], c[1] - b[1])
    cross, dot = u[0] * v[1] - u[1] * v[0], u[0] * v[0] + u[1] * v[1]
    return dot > 0 and abs(cross) <= tol * math.hypot(*u) * math.hypot(*v)


def axis_rectangle(points: Iterable[Sequence[float]],
                   rel_tol: float = 1e-9) -> tuple[float, float, float, float] | None:
    """``(x0, y0, width, height)`` of an axis-aligned rectangle, else ``None``.

    Coordinates closer than ``rel_tol`` times the rectangle's size count as equal
    (float noise from rotated references).
    """
    pts = ring(points)
    if len(pts) != 4:
        return None
    xs, ys = [p[0] for p in pts], [p[1] for p in pts]
    x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
    tol = rel_tol * max(x1 - x0, y1 - y0)
    for a, b in zip(pts, pts[1:] + pts[:1]):
        if abs(a[0] - b[0]) > tol and abs(a[1] - b[1]) > tol:
            return None
    if not all(min(abs(x - x0), abs(x - x1)) <= tol and min(abs(y - y0), abs(y - y1)) <= tol
               for x, y in pts):
        return None
    return x0, y0, x1 - x0, y1 - y0


def rounded(v: float) -> float:
    """Round to 1e-6 nm (hides float noise from transforms) and turn -0.0 into 0.0."""
    return round(v, 6) + 0.0


# -- output -------------------------------------------------------------------------

class LayoutBuilder:
    """Collects slots and keep-outs in layout coordinates and emits the layout dict.

    ``key`` arguments name the CAD element (``circle#c3``, ``LINE 2F``); they appear
    in the error lines.
    """

    def __init__(self, source: str, name: str):
        self.source = source
        self.name = name
        self.targets: list[dict] = []
        self.keepouts: list[dict] = []
        self.marks: list[dict] = []
        self.ignored: Counter[str] = Counter()
        self.notes: list[str] = []
        self.units: str | None = None       # where the drawing's unit came from, for a wrong-unit hint

    def fail(self, key: str | None, problem: str) -> NoReturn:
        """Raise the located error for ``key``."""
        raise InputError(self.source, key, problem)

    def _count(self) -> None:
        if len(self.targets) + len(self.keepouts) + len(self.marks) >= MAX_ELEMENTS:
            self.fail(None, f"more than {MAX_ELEMENTS} targets and keep-outs; an import may "
                            f"produce at most {MAX_ELEMENTS}")

    def _check(self, key: str, what: str, *values: float, **limits) -> None:
        for v in values:
            check_number(v, lambda problem: self.fail(key, f"{what} {problem}"), **limits)

    def _size(self, key: str, what: str, value: float) -> float:
        self._check(key, what, value, positive=True)
        return rounded(value)

    @staticmethod
    def _with_id(target_id: str | None, body: dict) -> dict:
        return {"id": target_id, **body} if target_id else body

    def particle(self, key: str, at: Point, diameter: float, target_id: str | None = None) -> None:
        """A particle slot centred at ``at`` (nm)."""
        self._count()
        self._check(key, "position", *at)
        d = self._size(key, "diameter", diameter)
        self.targets.append(self._with_id(target_id, {
            "kind": "particle", "at": [rounded(at[0]), rounded(at[1])], "diameter": d}))

    def rod(self, key: str, a: Point, b: Point, diameter: float, extension: float = 0.0,
            target_id: str | None = None) -> None:
        """A rod slot along the segment ``a``-``b`` (nm); ``extension`` is added to its
        length (caps beyond the end points, both ends together)."""
        self._count()
        self._check(key, "end point", *a, *b)
        dx, dy = b[0] - a[0], b[1] - a[1]
        if math.hypot(dx, dy) == 0:
            self.fail(key, "rod has zero length")
        length = self._size(key, "length", math.hypot(dx, dy) + extension)
        d = self._size(key, "diameter", diameter)
        angle = rounded(math.degrees(math.atan2(dy, dx)) % 180.0) % 180.0
        at = [rounded((a[0] + b[0]) / 2), rounded((a[1] + b[1]) / 2)]
        self.targets.append(self._with_id(target_id, {
            "kind": "rod", "at": at, "angle": angle, "length": length, "diameter": d}))

    def keepout(self, key: str, points: Iterable[Point], *, what: str = "keep-out") -> None:
        """A keep-out polygon (nm); repeated and closing vertices are dropped. With
        ``what="mark"``, an alignment mark (a keep-out that registers the layout)."""
        self._count()
        pts = [(rounded(x), rounded(y)) for x, y in points]
        for p in pts:
            self._check(key, f"{what} vertex", *p)
        corners = ring(pts, collinear=0.0)
        if len(corners) < 3:
            self.fail(key, f"{what} outline has {len(corners)} distinct corner(s), needs 3")
        twice_area = sum(p[0] * q[1] - q[0] * p[1] for p, q in zip(corners, corners[1:] + corners[:1]))
        if twice_area == 0:
            self.fail(key, f"{what} outline encloses no area")
        (self.marks if what == "mark" else self.keepouts).append({"polygon": [list(p) for p in corners]})

    def mark(self, key: str, points: Iterable[Point]) -> None:
        """An alignment mark's polygon (nm): a feature on the sample, a keep-out too."""
        self.keepout(key, points, what="mark")

    def ignore(self, what: str, count: int = 1) -> None:
        """Count an element the layout has no use for."""
        self.ignored[what] += count

    def build(self, area: Point, hint: str) -> dict:
        """The layout dict; ``hint`` says which elements make targets in this format."""
        self._check("area", "working area", *area)
        if min(area) <= 0:
            self.fail(None, f"working area must have a positive size, got {area[0]:g} x {area[1]:g} nm")
        if max(area) > IMPLAUSIBLE_SIDE:
            self.fail("area", f"working area {area[0]:g} x {area[1]:g} nm ({max(area) / 1e6:g} mm a side) is no "
                              f"AFM's: are the drawing's units right? ({self.units or 'its unit'})")
        if not self.targets:
            self.fail(None, f"no targets found ({hint})")
        doc: dict = {"format": FORMAT, "name": self.name,
                     "area": [rounded(area[0]), rounded(area[1])], "target": self.targets}
        if self.keepouts:
            doc["keepout"] = self.keepouts
        if self.marks:
            doc["mark"] = self.marks
        return doc

    def report(self, warnings: list[str] | None) -> None:
        """Append the ignored-element counts and notes to ``warnings`` (if given)."""
        if warnings is None:
            return
        warnings.extend(self.notes)
        warnings.extend(f"{self.source}: ignored {n} {what}" for what, n in sorted(self.ignored.items()))
