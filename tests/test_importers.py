"""CAD importers: SVG, GDSII and DXF drawings -> layout v1 dicts.

Files are generated here (plain SVG text, gdstk, ezdxf); every mapping, unit and frame
rule is checked against numbers worked out by hand, every bad file against its one
error line.
"""

from __future__ import annotations

import math

import ezdxf
import gdstk
import numpy as np
import pytest
from ezdxf import units as dxf_units
from hypothesis import given
from hypothesis import strategies as st
from nanoasm.cad.dxf import import_dxf
from nanoasm.cad.gds import import_gds
from nanoasm.cad.importers import import_layout
from nanoasm.cad.svg import import_svg

from nanoasm.errors import InputError

EXACT = 1e-6  # nm


def validated(doc: dict, source: str) -> dict:
    """Run the layout v1 validator over an importer's output (when it exists)."""
    layout = pytest.importorskip("nanoasm.cad.layout")
    layout.layout_from_dict(doc, source)
    return doc


def error_line(exc: pytest.ExceptionInfo) -> str:
    line = str(exc.value)
    assert isinstance(exc.value, InputError)
    assert "\n" not in line and "Traceback" not in line
    return line


def approx(values, expected, tol=EXACT):
    np.testing.assert_allclose(np.asarray(values, float), np.asarray(expected, float), rtol=0, atol=tol)


def by_kind(doc: dict, kind: str) -> list[dict]:
    return [t for t in doc["target"] if t["kind"] == kind]


# == SVG =============================================================================

def write_svg(tmp_path, body: str, root: str = 'viewBox="0 0 1000 500"', name: str = "chip.svg"):
    path = tmp_path / name
    path.write_text(f'<svg xmlns="http://www.w3.org/2000/svg" '
                    f'xmlns:xlink="http://www.w3.org/1999/xlink" {root}>\n{body}\n</svg>\n')
    return path


def test_svg_circle_is_particle_and_line_is_rod_with_y_flipped(tmp_path):
    path = write_svg(tmp_path, """
        <circle id="p1" cx="100" cy="100" r="10"/>
        <line id="r1" x1="200" y1="100" x2="300" y2="200" stroke-width="5"/>
        <circle cx="600" cy="250" r="25"/>""")
    doc = validated(import_svg(path), str(path))
    assert doc["format"] == "nanoasm.layout/1" and doc["name"] == "chip"
    assert doc["area"] == [1000.0, 500.0]
    p1, r1, p2 = doc["target"]
    assert p1 == {"id": "p1", "kind": "particle", "at": [100.0, 400.0], "diameter": 20.0}
    assert "id" not in p2 and p2["at"] == [600.0, 250.0] and p2["diameter"] == 50.0
    assert r1["id"] == "r1" and r1["kind"] == "rod"
    approx(r1["at"], [250.0, 350.0])
    approx([r1["angle"], r1["length"], r1["diameter"]], [135.0, 100 * math.sqrt(2), 5.0])
    assert "keepout" not in doc


def test_svg_scale_and_viewbox_origin(tmp_path):
    path = write_svg(tmp_path, '<circle cx="0" cy="50" r="5"/><circle cx="900" cy="550" r="5"/>',
                     root='viewBox="-100 50 1000 500" width="10cm" height="5cm"')
    doc = import_svg(path, scale=2.0)
    assert doc["area"] == [2000.0, 1000.0]
    approx(doc["target"][0]["at"], [200.0, 1000.0])  # top-left of the viewBox is y = 500
    approx(doc["target"][1]["at"], [2000.0, 0.0])
    assert doc["target"][0]["diameter"] == 20.0


def test_svg_area_from_width_and_height_in_absolute_units(tmp_path):
    path = write_svg(tmp_path, '<circle cx="10" cy="10" r="1mm"/>', root='width="96" height="2in"')
    doc = import_svg(path, scale=10.0)
    approx(doc["area"], [960.0, 1920.0])
    approx(doc["target"][0]["at"], [100.0, 1820.0])
    approx([doc["target"][0]["diameter"]], [2 * 96 / 25.4 * 10])


def test_svg_transforms_are_applied(tmp_path):
    path = write_svg(tmp_path, """
        <g transform="translate(500 250)">
          <g transform="rotate(90)">
            <circle id="c" cx="100" cy="0" r="10" transform="scale(2)"/>
            <line id="l" x1="0" y1="0" x2="50" y2="0" stroke-width="4"/>
          </g>
        </g>
        <g transform="scale(2 1)">
          <line id="h" x1="10" y1="100" x2="60" y2="100" stroke-width="4"/>
          <line id="v" x1="300" y1="100" x2="300" y2="200" stroke-width="4"/>
        </g>""")
    t = {x["id"]: x for x in validated(import_svg(path), str(path))["target"]}
    # rotate(90) maps (200, 0) to (0, 200): user (500, 450), layout (500, 50)
    approx(t["c"]["at"], [500.0, 50.0])
    assert t["c"]["diameter"] == pytest.approx(40.0, abs=EXACT)
    # the line runs from (500, 250) to (500, 300) in user units: downwards, i.e. -90 deg
    approx(t["l"]["at"], [500.0, 225.0])
    approx([t["l"]["angle"], t["l"]["length"], t["l"]["diameter"]], [90.0, 50.0, 4.0])
    # scale(2 1) stretches along the horizontal line (width kept) and across the vertical one
    approx([t["h"]["length"], t["h"]["diameter"], t["h"]["angle"]], [100.0, 4.0, 0.0])
    approx([t["v"]["length"], t["v"]["diameter"], t["v"]["angle"]], [100.0, 8.0, 90.0])
    approx(t["v"]["at"], [600.0, 350.0])


def test_svg_circle_stretched_into_an_ellipse_is_refused(tmp_path):
    path = write_svg(tmp_path, '<circle id="c3" cx="10" cy="10" r="5" transform="scale(2 1)"/>')
    with pytest.raises(InputError) as exc:
        import_svg(path)
    assert error_line(exc).startswith(f"{path}: circle#c3: its transform stretches or skews")


def test_svg_stroke_width_from_group_style_and_css(tmp_path):
    path = write_svg(tmp_path, """
        <style>.thick { stroke-width: 7 }</style>
        <g stroke-width="3"><line id="a" x1="10" y1="10" x2="110" y2="10"/></g>
        <line id="b" x1="10" y1="50" x2="110" y2="50" style="stroke:black; stroke-width:6"/>
        <line id="c" class="thick" x1="10" y1="90" x2="110" y2="90"/>
        <line id="d" x1="10" y1="130" x2="110" y2="130" stroke-width="0.5mm"/>""")
    t = {x["id"]: x for x in import_svg(path)["target"]}
    approx([t["a"]["diameter"], t["b"]["diameter"], t["c"]["diameter"], t["d"]["diameter"]],
           [3.0, 6.0, 7.0, 0.5 * 96 / 25.4])


def test_svg_round_or_square_caps_add_the_stroke_width_to_the_length(tmp_path):
    path = write_svg(tmp_path, """
        <line id="butt" x1="10" y1="10" x2="110" y2="10" stroke-width="8"/>
        <line id="round" x1="10" y1="50" x2="110" y2="50" stroke-width="8" stroke-linecap="round"/>
        <line id="square" x1="10" y1="90" x2="110" y2="90" stroke-width="8" stroke-linecap="square"/>""")
    t = {x["id"]: x for x in import_svg(path)["target"]}
    assert [t[k]["length"] for k in ("butt", "round", "square")] == [100.0, 108.0, 108.0]


def test_svg_use_instances_take_the_use_id_and_position(tmp_path):
    path = write_svg(tmp_path, """
        <defs><circle id="proto" cx="0" cy="0" r="5"/></defs>
        <use id="u1" xlink:href="#proto" x="100" y="100"/>
        <use id="u2" href="#proto" x="200" y="100"/>""")
    doc = validated(import_svg(path), str(path))
    assert [(t["id"], t["at"]) for t in doc["target"]] == [("u1", [100.0, 400.0]), ("u2", [200.0, 400.0])]


def test_svg_keepout_groups_and_classes(tmp_path):
    path = write_svg(tmp_path, """
        <circle id="p" cx="500" cy="250" r="10"/>
        <g class="pads keepout" transform="translate(10 10)">
          <rect x="0" y="0" width="100" height="50"/>
          <g><polygon points="200,0 300,0 250,80"/></g>
        </g>
        <g id="keepout-marks"><circle cx="900" cy="400" r="40"/></g>
        <path class="keepout"
              d="M 700 100 L 800 100 L 800 150 Q 750 200 700 150 Z M 600 20 h 50 v 30 h -50 z"/>
        <rect x="0" y="450" width="50" height="50"/>""")
    warnings: list[str] = []
    doc = validated(import_svg(path, warnings=warnings), str(path))
    assert len(doc["target"]) == 1
    rect, tri, disc, curved, square = (k["polygon"] for k in doc["keepout"])
    assert rect == [[10.0, 490.0], [110.0, 490.0], [110.0, 440.0], [10.0, 440.0]]
    assert tri == [[210.0, 490.0], [310.0, 490.0], [260.0, 410.0]]
    radii = [math.hypot(x - 900, y - 100) for x, y in disc]
    assert len(disc) >= 16 and max(radii) <= 40 + EXACT and min(radii) >= 40 - 1.0
    assert curved[:3] == [[700.0, 400.0], [800.0, 400.0], [800.0, 350.0]]
    assert min(y for _, y in curved) == pytest.approx(325.0, abs=1.0)  # the quadratic's apex
    assert square == [[600.0, 480.0], [650.0, 480.0], [650.0, 450.0], [600.0, 450.0]]
    assert warnings == [f"{path}: ignored 1 <rect>"]


def test_svg_keepout_class_option_and_inkscape_layer_label(tmp_path):
    path = write_svg(tmp_path, """
        <circle cx="500" cy="250" r="10"/>
        <g inkscape:label="Electrodes" inkscape:groupmode="layer"
           xmlns:inkscape="http://www.inkscape.org/namespaces/inkscape">
          <rect x="0" y="0" width="10" height="10"/></g>
        <rect class="keepout" x="20" y="0" width="10" height="10"/>""")
    doc = import_svg(path, keepout_class="electrodes")
    assert [k["polygon"][0] for k in doc["keepout"]] == [[0.0, 500.0]]
    assert len(import_svg(path)["keepout"]) == 1  # default class: only the second rect


def test_svg_ignored_elements_are_counted_not_printed(tmp_path, capsys):
    path = write_svg(tmp_path, """
        <circle cx="50" cy="50" r="5"/><ellipse cx="1" cy="1" rx="2" ry="1"/>
        <path d="M 0 0 L 5 5"/><path d="M 9 9 L 5 5"/><text x="1" y="1">chip 7</text>""")
    warnings: list[str] = []
    import_svg(path, warnings=warnings)
    assert warnings == [f"{path}: ignored 1 <ellipse>", f"{path}: ignored 2 <path>",
                        f"{path}: ignored 1 <text>"]
    assert capsys.readouterr() == ("", "")


def test_svg_undrawn_and_hidden_content_is_not_a_target(tmp_path):
    path = write_svg(tmp_path, """
        <defs><circle id="d" cx="1" cy="1" r="1"/></defs>
        <clipPath id="cp"><circle cx="2" cy="2" r="1"/></clipPath>
        <mask id="m"><circle cx="3" cy="3" r="1"/></mask>
        <marker id="mk"><circle cx="4" cy="4" r="1"/></marker>
        <symbol id="sym"><circle cx="5" cy="5" r="1"/></symbol>
        <circle cx="6" cy="6" r="1" display="none"/>
        <g visibility="hidden"><circle cx="7" cy="7" r="1"/></g>
        <circle id="shown" cx="8" cy="8" r="1"/>
        <use id="s1" href="#sym" x="100"/>""")
    warnings: list[str] = []
    doc = import_svg(path, warnings=warnings)
    assert [(t.get("id"), t["at"]) for t in doc["target"]] == [("shown", [8.0, 492.0]),
                                                                ("s1", [105.0, 495.0])]
    assert warnings == [f"{path}: ignored 1 hidden element(s)"]


def test_svg_plain_doctype_is_accepted(tmp_path):
    path = tmp_path / "dt.svg"
    path.write_text('<?xml version="1.0" standalone="no"?>\n'
                    '<!DOCTYPE svg PUBLIC "-//W3C//DTD SVG 1.1//EN" '
                    '"http://www.w3.org/Graphics/SVG/1.1/DTD/svg11.dtd">\n'
                    '<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 10 10">'
                    '<circle cx="5" cy="5" r="1"/></svg>')
    assert import_svg(path)["target"][0]["at"] == [5.0, 5.0]


BOMB = ('<?xml version="1.0"?>\n<!DOCTYPE lolz [<!ENTITY lol "lol">'
        '<!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">'
        '<!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">]>\n'
        '<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 10 10"><text>&lol3;</text>'
        '<circle cx="5" cy="5" r="1"/></svg>')
XXE = ('<?xml version="1.0"?>\n<!DOCTYPE svg [<!ENTITY x SYSTEM "file:///etc/passwd">]>\n'
       '<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 10 10"><text>&x;</text>'
       '<circle cx="5" cy="5" r="1"/></svg>')
NS = 'xmlns="http://www.w3.org/2000/svg"'


def svg10(body: str) -> bytes:
    return f'<svg {NS} viewBox="0 0 10 10">{body}</svg>'.encode()


@pytest.mark.parametrize("content, problem", [
    (b"", "file is empty"),
    (b"  \n\t", "file is empty"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "binary file, expected SVG text"),
    (f'<svg {NS} viewBox="0 0 10 10"><circle cx="5" cy="5" r="1"/>'.encode(), "truncated XML: "),
    (svg10('<circle cx="5" r="1">'), "not valid XML: mismatched tag"),
    (b"hello", "not valid XML: syntax error"),
    (BOMB.encode(), "XML entity declarations are not allowed (unsafe)"),
    (XXE.encode(), "XML entity declarations are not allowed (unsafe)"),
    (b"<html><body>hi</body></html>", "not an SVG file (the root element is <html>)"),
    (f'<svg {NS}><circle r="1"/></svg>'.encode(),
     "svg: no working area: the root <svg> has neither a viewBox nor a width and a height"),
    (f'<svg {NS} width="100%" height="100%"><circle r="1"/></svg>'.encode(),
     "svg: width is a percentage; give the root <svg> a viewBox"),
    (f'<svg {NS} viewBox="0 0 10"><circle r="1"/></svg>'.encode(),
     "svg: viewBox must be four numbers 'min-x min-y width height', got '0 0 10'"),
    (f'<svg {NS} viewBox="0 0 10 -5"><circle r="1"/></svg>'.encode(),
     "svg: viewBox width and height must be positive, got '0 0 10 -5'"),
    (svg10('<circle id="c3" cx="5" cy="5" r="-5"/>'),
     "circle#c3: r must be positive, got -5"),
    (svg10('<circle cx="5" cy="5"/>'), "circle[1]: r is missing"),
    (svg10('<circle cx="5" r="x"/>'), "circle[1]: r is not a length: 'x'"),
    (svg10('<circle cx="1e999" r="1"/>'),
     "circle[1]: cx is not finite: '1e999'"),
    (svg10('<circle cx="nan" r="1"/>'), "circle[1]: cx is not a length"),
    (svg10('<circle r="2em"/>'), "circle[1]: r uses the unit 'em'"),
    (svg10('<circle r="1" transform="scale(1e300) scale(1e300)"/>'),
     "circle[1]: transform is not finite"),
    (svg10('<line id="l1" x1="1" x2="5"/>'),
     "line#l1: stroke-width is missing (it sets the rod diameter)"),
    (svg10('<line x1="1" x2="5" stroke-width="0"/>'),
     "line[1]: stroke-width must be positive, got 0"),
    (svg10('<line x1="1" x2="1" stroke-width="1"/>'),
     "line[1]: line has zero length"),
    (svg10('<rect width="1" height="1"/>'),
     "no targets found (expected <circle> elements for particles or <line> elements for rods)"),
    (svg10('<circle r="1"/><g class="keepout"><line x2="3" stroke-width="1"/></g>'),
     "line[1]: a <line> cannot be a keep-out"),
    (svg10('<circle r="1"/><path class="keepout" d="M 0 0 L 5 0 L 5 5"/>'),
     "path[1]: keep-out outline is not closed (end the path with Z)"),
    (svg10('<circle r="1"/><polygon class="keepout" points="0,0 5,0 5"/>'),
     "polygon[1]: points must be pairs of numbers, got '0,0 5,0 5'"),
    (svg10('<circle r="1"/><polygon class="keepout" points="0,0 5,0 9,0"/>'),
     "polygon[1]: keep-out outline has 2 distinct corner(s), needs 3"),
    (svg10('<circle r="1"/><path class="keepout" d="M 0 0 L 5 0 L 0 0 Z"/>'),
     "path[1]: keep-out outline has 2 distinct corner(s), needs 3"),
    (svg10('<circle r="1"/><rect class="keepout" width="5" height="1e999"/>'),
     "rect[1]: height is not finite: '1e999'"),
    (svg10('<circle r="1"/><path class="keepout" d="nonsense"/>'),
     "path[1]: keep-out shape has no outline"),
])
def test_svg_bad_files_give_one_line(tmp_path, content, problem):
    path = tmp_path / "chip.svg"
    path.write_bytes(content)
    with pytest.raises(InputError) as exc:
        import_svg(path)
    line = error_line(exc)
    assert line.startswith(f"{path}: {problem}"), line


def test_svg_missing_file_and_directory(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        import_svg(tmp_path / "absent.svg")
    with pytest.raises(InputError, match="is a directory"):
        import_svg(tmp_path)


@given(x1=st.floats(0, 1000), y1=st.floats(0, 500), x2=st.floats(0, 1000), y2=st.floats(0, 500),
       scale=st.floats(0.01, 100))
def test_svg_line_invariants(tmp_path_factory, x1, y1, x2, y2, scale):
    length = math.hypot(x2 - x1, y2 - y1)
    if length < 1e-3:
        return
    path = write_svg(tmp_path_factory.mktemp("svg"),
                     f'<line x1="{x1!r}" y1="{y1!r}" x2="{x2!r}" y2="{y2!r}" stroke-width="1"/>')
    rod = import_svg(path, scale=scale)["target"][0]
    assert 0 <= rod["angle"] < 180
    tol = 1e-5 * scale * 1000 + EXACT
    assert rod["length"] == pytest.approx(length * scale, abs=tol)
    approx(rod["at"], [(x1 + x2) / 2 * scale, (500 - (y1 + y2) / 2) * scale], tol)
    a = math.radians(rod["angle"])
    # the axis is parallel to the flipped line
    assert abs(math.cos(a) * (y1 - y2) - math.sin(a) * (x2 - x1)) <= 1e-6 * length + 1e-9


# == GDSII ===========================================================================

def gds_lib(unit: float = 1e-6, precision: float = 1e-12) -> tuple[gdstk.Library, gdstk.Cell]:
    lib = gdstk.Library(unit=unit, precision=precision)
    return lib, lib.new_cell("TOP")


def write_gds(tmp_path, lib: gdstk.Library, name: str = "chip.gds"):
    path = tmp_path / name
    lib.write_gds(str(path))
    return path


def test_gds_mapping_in_micrometre_units(tmp_path):
    lib, top = gds_lib()
    top.add(gdstk.rectangle((1, 1), (11, 6), layer=0))                       # area, origin (1, 1) um
    top.add(gdstk.ellipse((3, 2), 0.05, tolerance=1e-5, layer=1))             # fine circle
    top.add(gdstk.ellipse((4, 2), 0.05, layer=1))                              # default: a hexagon
    top.add(gdstk.FlexPath([(5, 3), (6, 4)], 0.1, simple_path=True, layer=2))  # flush ends
    top.add(gdstk.FlexPath([(7, 3), (7, 4.5)], 0.08, ends="round", simple_path=True, layer=2))
    top.add(gdstk.rectangle((8, 2), (8.6, 2.1), layer=2))                      # rod rectangle
    top.add(gdstk.rectangle((2, 4), (3, 5), layer=3))                          # keep-out
    top.add(gdstk.rectangle((0, 0), (1, 1), layer=7))                          # ignored
    path = write_gds(tmp_path, lib)
    warnings: list[str] = []
    doc = validated(import_gds(path, warnings=warnings), str(path))
    assert doc["area"] == [10000.0, 5000.0] and doc["name"] == "chip"
    fine, hexagon = by_kind(doc, "particle")
    approx(fine["at"], [2000.0, 1000.0], 1e-3)
    approx(hexagon["at"], [3000.0, 1000.0], 1e-3)
    assert len(gdstk.ellipse((0, 0), 0.05).points) == 6
    for p in (fine, hexagon):
        assert p["diameter"] == pytest.approx(100.0, rel=0.005)
    diagonal, capsule, rect = by_kind(doc, "rod")
    approx(diagonal["at"], [4500.0, 2500.0])
    approx([diagonal["angle"], diagonal["length"], diagonal["diameter"]], [45.0, 1000 * math.sqrt(2), 100.0])
    approx(capsule["at"], [6000.0, 2750.0])
    approx([capsule["angle"], capsule["length"], capsule["diameter"]], [90.0, 1580.0, 80.0])
    approx(rect["at"], [7300.0, 1050.0])
    approx([rect["angle"], rect["length"], rect["diameter"]], [0.0, 600.0, 100.0])
    assert doc["keepout"] == [{"polygon": [[1000.0, 3000.0], [2000.0, 3000.0], [2000.0, 4000.0],
                                           [1000.0, 4000.0]]}]
    assert warnings == [f"{path}: ignored 1 shape(s) on layer 7/0"]


def test_gds_units_nanometre_library(tmp_path):
    lib, top = gds_lib(unit=1e-9, precision=1e-11)
    top.add(gdstk.rectangle((0, 0), (2000, 1000), layer=0))
    top.add(gdstk.ellipse((500, 500), 60, tolerance=0.01, layer=1))
    doc = import_gds(write_gds(tmp_path, lib))
    assert doc["area"] == [2000.0, 1000.0]
    approx(doc["target"][0]["at"], [500.0, 500.0], 1e-3)
    assert doc["target"][0]["diameter"] == pytest.approx(120.0, rel=0.005)


@pytest.mark.parametrize("angle", [0.0, 17.0, 30.0, 89.0, 135.0, 179.5])
def test_gds_rotated_rectangle_rod(tmp_path, angle):
    lib, top = gds_lib(precision=1e-10)
    top.add(gdstk.rectangle((0, 0), (10, 10), layer=0))
    rect = gdstk.rectangle((-0.6, -0.05), (0.6, 0.05), layer=2)
    rect.rotate(math.radians(angle))
    rect.translate(5, 5)
    top.add(rect)
    rod = import_gds(write_gds(tmp_path, lib))["target"][0]
    approx(rod["at"], [5000.0, 5000.0], 0.1)
    approx([rod["length"], rod["diameter"]], [1200.0, 100.0], 0.1)
    assert min(abs(rod["angle"] - angle), 180 - abs(rod["angle"] - angle)) < 0.01


def test_gds_references_and_arrays_are_flattened(tmp_path):
    lib, top = gds_lib()
    dot = lib.new_cell("DOT")
    dot.add(gdstk.ellipse((0, 0), 0.05, tolerance=1e-5, layer=1))
    top.add(gdstk.rectangle((0, 0), (10, 10), layer=0))
    top.add(gdstk.Reference(dot, (1, 1), columns=3, rows=2, spacing=(2, 3)))
    top.add(gdstk.Reference(dot, (9, 9), magnification=2))
    doc = validated(import_gds(write_gds(tmp_path, lib)), "chip.gds")
    centres = sorted(tuple(round(v) for v in t["at"]) for t in doc["target"])
    assert centres == sorted([(1000 + 2000 * i, 1000 + 3000 * j) for i in range(3) for j in range(2)]
                             + [(9000, 9000)])
    assert sorted(round(t["diameter"]) for t in doc["target"]) == [100] * 6 + [200]


def test_gds_circle_split_by_the_writer_is_rejoined(tmp_path):
    lib, top = gds_lib()
    top.add(gdstk.rectangle((0, 0), (10, 10), layer=0))
    circle = gdstk.ellipse((4, 6), 1.5, tolerance=1e-5, layer=1)
    assert len(circle.points) > 199  # gdstk.write_gds splits polygons above 199 vertices
    top.add(circle)
    path = write_gds(tmp_path, lib)
    assert len(gdstk.read_gds(str(path)).cells[0].polygons) > 2
    doc = validated(import_gds(path), str(path))
    [particle] = doc["target"]
    approx(particle["at"], [4000.0, 6000.0], 1e-3)
    assert particle["diameter"] == pytest.approx(3000.0, rel=1e-4)


def test_gds_layer_options_and_area_option(tmp_path):
    lib, top = gds_lib()
    top.add(gdstk.ellipse((1, 1), 0.1, tolerance=1e-5, layer=10, datatype=2))
    top.add(gdstk.FlexPath([(2, 2), (3, 2)], 0.1, simple_path=True, layer=11))
    top.add(gdstk.rectangle((4, 4), (5, 5), layer=12, datatype=1))
    path = write_gds(tmp_path, lib)
    doc = import_gds(path, particle_layer="10/2", rod_layer=(11, 0), keepout_layer=(12, 1), area=(6000, 7000))
    assert doc["area"] == [6000.0, 7000.0]
    approx(doc["target"][0]["at"], [1000.0, 1000.0], 1e-3)
    approx(doc["target"][1]["at"], [2500.0, 2000.0])
    assert len(doc["keepout"]) == 1
    with pytest.raises(InputError) as exc:
        import_gds(path)
    assert error_line(exc) == f"{path}: no working area: draw one rectangle on layer 0/0 or give --area W H"


def test_gds_area_given_twice_is_refused(tmp_path):
    lib, top = gds_lib()
    top.add(gdstk.rectangle((0, 0), (1, 1), layer=0))
    top.add(gdstk.ellipse((0.5, 0.5), 0.1, layer=1))
    path = write_gds(tmp_path, lib)
    with pytest.raises(InputError) as exc:
        import_gds(path, area=(1000, 1000))
    assert error_line(exc) == (f"{path}: --area: the file already has a working-area rectangle "
                               "on layer 0/0; drop --area")


def test_gds_cell_selection(tmp_path):
    lib, top = gds_lib()
    other = lib.new_cell("OTHER")
    for c, x in ((top, 1), (other, 2)):
        c.add(gdstk.rectangle((0, 0), (5, 5), layer=0))
        c.add(gdstk.ellipse((x, 1), 0.1, tolerance=1e-5, layer=1))
    path = write_gds(tmp_path, lib)
    with pytest.raises(InputError) as exc:
        import_gds(path)
    assert error_line(exc) == f"{path}: 2 top cells (OTHER, TOP); choose one with --cell"
    approx(import_gds(path, cell="OTHER")["target"][0]["at"], [2000.0, 1000.0], 1e-3)
    with pytest.raises(InputError) as exc:
        import_gds(path, cell="MAIN")
    assert error_line(exc) == f"{path}: --cell: no cell 'MAIN' (cells: OTHER, TOP)"


def _gds_with(tmp_path, *shapes):
    lib, top = gds_lib()
    top.add(gdstk.rectangle((0, 0), (10, 10), layer=0), *shapes)
    return write_gds(tmp_path, lib)


@pytest.mark.parametrize("shape, problem", [
    (gdstk.rectangle((1, 1), (2, 2), layer=1), "has 4 corners; a particle must be a circle polygon"),
    (gdstk.ellipse((5, 5), (0.3, 0.2), tolerance=1e-5, layer=1), "is not round"),
    (gdstk.ellipse((5, 5), 0.3, initial_angle=0, final_angle=math.pi, tolerance=1e-5, layer=1),
     "is not round"),
    (gdstk.Polygon([(1, 1), (2, 1), (2, 2), (1.5, 2.5), (1, 2)], layer=2),
     "has 5 corners; a rod polygon must be a rectangle"),
    (gdstk.Polygon([(1, 1), (3, 1), (3.5, 1.5), (1.5, 1.5)], layer=2), "is not a rectangle"),
    (gdstk.rectangle((1, 1), (2, 2), layer=2), "is a square"),
    (gdstk.FlexPath([(1, 1), (2, 1), (2, 2)], 0.1, simple_path=True, layer=2), "path bends"),
    (gdstk.rectangle((1, 1), (2, 2), layer=0), "2 shapes on the working-area layer"),
])
def test_gds_uninterpretable_shapes(tmp_path, shape, problem):
    path = _gds_with(tmp_path, shape)
    with pytest.raises(InputError) as exc:
        import_gds(path)
    line = error_line(exc)
    assert line.startswith(f"{path}: ") and problem in line, line


def test_gds_rotated_area_and_no_targets(tmp_path):
    lib, top = gds_lib()
    area = gdstk.rectangle((0, 0), (10, 10), layer=0)
    area.rotate(0.3)
    top.add(area, gdstk.ellipse((1, 1), 0.1, layer=1))
    path = write_gds(tmp_path, lib)
    with pytest.raises(InputError, match="the working area must be an axis-aligned rectangle"):
        import_gds(path)
    path = _gds_with(tmp_path, gdstk.rectangle((1, 1), (2, 2), layer=3))
    with pytest.raises(InputError) as exc:
        import_gds(path)
    assert error_line(exc) == (f"{path}: no targets found (expected circle polygons on layer 1/0 "
                               "or paths/rectangles on layer 2/0)")


def test_gds_bad_files_give_one_line(tmp_path, capfd):
    lib, top = gds_lib()
    top.add(gdstk.rectangle((0, 0), (10, 10), layer=0), gdstk.ellipse((5, 5), 0.1, layer=1))
    good = write_gds(tmp_path, lib).read_bytes()
    cases = {
        b"": "file is empty",
        b"hello, this is text\n": "not a GDSII file (it does not start with a HEADER record)",
        good[:len(good) // 2]: "truncated GDSII file (it ends before the ENDLIB record)",
        good[:6] + b"\x00\x03\x01\x02" + good[10:]: "corrupt GDSII file (bad record at byte 6)",
        bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8)): "not a GDSII file",
        b'<svg xmlns="http://www.w3.org/2000/svg"/>': "not a GDSII file",
    }
    for content, problem in cases.items():
        path = tmp_path / "bad.gds"
        path.write_bytes(content)
        with pytest.raises(InputError) as exc:
            import_gds(path)
        assert error_line(exc).startswith(f"{path}: {problem}")
    assert capfd.readouterr() == ("", "")  # gdstk never got to print its own complaints


def test_gds_layer_option_errors(tmp_path):
    path = _gds_with(tmp_path, gdstk.ellipse((5, 5), 0.1, layer=1))
    with pytest.raises(InputError) as exc:
        import_gds(path, rod_layer="1/0")
    assert error_line(exc) == "--rod-layer: is the same layer 1/0 as --particle-layer"
    for bad in ("1-0", (1,), (1, -2), (1.5, 0), "a/b"):
        with pytest.raises(InputError, match="^--keepout-layer: must"):
            import_gds(path, keepout_layer=bad)


# == DXF =============================================================================

def dxf_doc(insunits: int | None = dxf_units.InsertUnits.Microns):
    doc = ezdxf.new("R2010")
    if insunits is not None:
        doc.header["$INSUNITS"] = int(insunits)
    return doc, doc.modelspace()


def save_dxf(tmp_path, doc, name: str = "chip.dxf"):
    path = tmp_path / name
    doc.saveas(path)
    return path


def test_dxf_mapping_in_micrometres(tmp_path):
    doc, msp = dxf_doc()
    msp.add_lwpolyline([(1, 1), (11, 1), (11, 6), (1, 6)], close=True, dxfattribs={"layer": "Area"})
    msp.add_circle((3, 2), 0.05)
    line = msp.add_line((5, 3), (6, 4))
    msp.add_lwpolyline([(7, 3), (7, 4.5)], dxfattribs={"const_width": 0.08})
    msp.add_lwpolyline([(2, 4), (3, 4, 0, 0, 1), (3, 5), (2, 5)], format="xyseb", close=True)
    msp.add_text("chip 7")
    path = save_dxf(tmp_path, doc)
    warnings: list[str] = []
    out = validated(import_dxf(path, rod_diameter=80, warnings=warnings), str(path))
    assert out["area"] == [10000.0, 5000.0] and out["name"] == "chip"
    particle, diagonal, wide = out["target"]
    assert particle == {"kind": "particle", "at": [2000.0, 1000.0], "diameter": 100.0}
    approx(diagonal["at"], [4500.0, 2500.0])
    approx([diagonal["angle"], diagonal["length"], diagonal["diameter"]], [45.0, 1000 * math.sqrt(2), 80.0])
    approx([wide["angle"], wide["length"], wide["diameter"]], [90.0, 1500.0, 80.0])
    polygon = np.array(out["keepout"][0]["polygon"])
    # the bulge 1 edge is a half circle of radius 500 nm bulging right of x = 2000
    arc = polygon[polygon[:, 0] > 2000 + 1e-6]
    approx(np.hypot(arc[:, 0] - 2000, arc[:, 1] - 3500), np.full(len(arc), 500.0), 1.0)
    assert arc[:, 0].max() == pytest.approx(2500.0, abs=1.0) and len(arc) >= 8
    assert warnings == [f"{path}: ignored 1 TEXT"]
    assert line.dxf.handle


@pytest.mark.parametrize("insunits, scale, factor", [
    (dxf_units.InsertUnits.Millimeters, None, 1e6),
    (dxf_units.InsertUnits.Nanometers, None, 1.0),
    (dxf_units.InsertUnits.Inches, None, 25.4e6),
    (dxf_units.InsertUnits.Unitless, None, 1.0),
    (dxf_units.InsertUnits.Unitless, 2.5, 2.5),
    (dxf_units.InsertUnits.Millimeters, 3.0, 3.0),   # --scale overrides $INSUNITS
])
def test_dxf_units(tmp_path, insunits, scale, factor):
    doc, msp = dxf_doc(insunits)
    msp.add_lwpolyline([(0, 0), (0.004, 0), (0.004, 0.002), (0, 0.002)], close=True,
                       dxfattribs={"layer": "AREA"})
    msp.add_circle((0.001, 0.0005), 0.0001)
    out = import_dxf(save_dxf(tmp_path, doc), scale=scale)
    approx(out["area"], [0.004 * factor, 0.002 * factor], 1e-9 * factor)
    approx(out["target"][0]["at"], [0.001 * factor, 0.0005 * factor], 1e-9 * factor)
    assert out["target"][0]["diameter"] == pytest.approx(0.0002 * factor, rel=1e-12)


def test_dxf_line_without_rod_diameter_names_the_handle(tmp_path):
    doc, msp = dxf_doc()
    msp.add_circle((1, 1), 0.1)
    line = msp.add_line((2, 2), (3, 2))
    path = save_dxf(tmp_path, doc)
    with pytest.raises(InputError) as exc:
        import_dxf(path, area=(5000, 5000))
    assert error_line(exc) == (f"{path}: LINE {line.dxf.handle}: no rod diameter "
                               "(DXF lines have no width); give --rod-diameter")


def test_dxf_block_references_are_expanded(tmp_path):
    doc, msp = dxf_doc()
    block = doc.blocks.new("DOT")
    block.add_circle((0, 0), 0.05)
    block.add_line((0.2, 0), (0.7, 0))
    msp.add_blockref("DOT", (2, 2))
    msp.add_blockref("DOT", (5, 5), dxfattribs={"xscale": 2, "yscale": 2, "rotation": 90})
    out = validated(import_dxf(save_dxf(tmp_path, doc), rod_diameter=50, area=(10000, 10000)), "chip.dxf")
    p1, r1, p2, r2 = out["target"]
    approx(p1["at"], [2000.0, 2000.0])
    approx(p2["at"], [5000.0, 5000.0])
    assert (p1["diameter"], p2["diameter"]) == (100.0, 200.0)
    approx(r1["at"], [2450.0, 2000.0])
    approx(r2["at"], [5000.0, 5900.0])
    approx([r1["angle"], r1["length"], r2["angle"], r2["length"]], [0.0, 500.0, 90.0, 1000.0])


def test_dxf_minsert_array(tmp_path):
    doc, msp = dxf_doc()
    block = doc.blocks.new("DOT")
    block.add_circle((0, 0), 0.05)
    msp.add_blockref("DOT", (1, 1), dxfattribs={"column_count": 3, "row_count": 2,
                                                "column_spacing": 2, "row_spacing": 3})
    out = validated(import_dxf(save_dxf(tmp_path, doc), area=(10000, 10000)), "chip.dxf")
    assert sorted(tuple(t["at"]) for t in out["target"]) == sorted(
        (1000.0 + 2000 * i, 1000.0 + 3000 * j) for i in range(3) for j in range(2))


def test_dxf_area_rules(tmp_path):
    doc, msp = dxf_doc()
    msp.add_circle((1, 1), 0.1)
    msp.add_circle((2, 2), 0.1, dxfattribs={"layer": "AREA"})
    msp.add_lwpolyline([(0, 0), (5, 0), (5, 5), (0, 5), (0, 0)], dxfattribs={"layer": "area"})
    path = save_dxf(tmp_path, doc)
    warnings: list[str] = []
    out = import_dxf(path, warnings=warnings)
    assert out["area"] == [5000.0, 5000.0] and len(out["target"]) == 1
    assert warnings == [f"{path}: ignored 1 CIRCLE on layer AREA"]
    with pytest.raises(InputError) as exc:
        import_dxf(path, area=(1, 1))
    assert error_line(exc) == (f"{path}: --area: the drawing already has a working area "
                               "on layer AREA; drop --area")

    msp.add_lwpolyline([(0, 0), (5, 0), (5, 5), (0, 5)], close=True, dxfattribs={"layer": "AREA"})
    with pytest.raises(InputError, match="layer AREA: 2 closed polylines; expected one rectangle"):
        import_dxf(save_dxf(tmp_path, doc))

    doc, msp = dxf_doc()
    msp.add_circle((1, 1), 0.1)
    msp.add_lwpolyline([(0, 0), (5, 0), (6, 5), (0, 5)], close=True, dxfattribs={"layer": "AREA"})
    with pytest.raises(InputError, match="the working area must be an axis-aligned rectangle"):
        import_dxf(save_dxf(tmp_path, doc))

    doc, msp = dxf_doc()
    msp.add_circle((1, 1), 0.1)
    path = save_dxf(tmp_path, doc)
    with pytest.raises(InputError) as exc:
        import_dxf(path)
    assert error_line(exc) == (f"{path}: no working area: draw a closed rectangle (LWPOLYLINE) "
                               "on layer AREA or give --area W H")


def _dxf_text(tmp_path) -> tuple[str, str]:
    doc, msp = dxf_doc()
    circle = msp.add_circle((1, 1), 0.25)
    msp.add_lwpolyline([(0, 0), (5, 0), (5, 5), (0, 5)], close=True, dxfattribs={"layer": "AREA"})
    return save_dxf(tmp_path, doc).read_text(), circle.dxf.handle


@pytest.mark.parametrize("edit, problem", [
    (lambda t: "", "file is empty"),
    (lambda t: t[: len(t) // 2], "truncated DXF file (it does not end with 0/EOF)"),
    (lambda t: "\x00\x01\x02" + t, "binary file, expected DXF"),
    (lambda t: "hello world\n", "not a DXF file (it starts with 'hello world')"),
    (lambda t: '<svg xmlns="http://www.w3.org/2000/svg"/>\n', "not a DXF file"),
    (lambda t: t.replace(" 40\n0.25\n", " 40\nabc\n", 1), 'damaged DXF file: Invalid tag (40, "abc")'),
    (lambda t: t.replace(" 40\n0.25\n", " 40\n-5\n", 1),
     "CIRCLE {h}: radius must be a positive number, got -5"),
    (lambda t: t.replace(" 40\n0.25\n", " 40\nnan\n", 1),
     "CIRCLE {h}: radius must be a positive number, got nan"),
    (lambda t: t.replace(" 20\n1.0\n 30\n0.0\n 40\n", " 20\n1e999\n 30\n0.0\n 40\n", 1),
     "CIRCLE {h}: position must be finite, got inf"),
])
def test_dxf_bad_files_give_one_line(tmp_path, edit, problem):
    text, handle = _dxf_text(tmp_path)
    path = tmp_path / "bad.dxf"
    path.write_bytes(edit(text).encode("latin-1"))
    with pytest.raises(InputError) as exc:
        import_dxf(path)
    line = error_line(exc)
    assert line.startswith(f"{path}: {problem.format(h=handle)}"), line


def test_dxf_no_targets_and_open_polyline(tmp_path):
    doc, msp = dxf_doc()
    msp.add_lwpolyline([(0, 0), (5, 0), (5, 5), (0, 5)], close=True, dxfattribs={"layer": "AREA"})
    msp.add_lwpolyline([(1, 1), (2, 1), (2, 2)])
    msp.add_lwpolyline([(3, 3), (4, 3), (4, 4)], close=True)
    path = save_dxf(tmp_path, doc)
    with pytest.raises(InputError) as exc:
        import_dxf(path)
    assert error_line(exc) == (f"{path}: no targets found (expected CIRCLE entities for particles "
                               "or LINE entities for rods)")


def test_dxf_binary_format(tmp_path):
    doc, msp = dxf_doc()
    msp.add_lwpolyline([(0, 0), (5, 0), (5, 5), (0, 5)], close=True, dxfattribs={"layer": "AREA"})
    msp.add_circle((1, 2), 0.25)
    path = tmp_path / "bin.dxf"
    doc.saveas(path, fmt="bin")
    assert path.read_bytes().startswith(b"AutoCAD Binary DXF")
    assert import_dxf(path)["target"] == [{"kind": "particle", "at": [1000.0, 2000.0], "diameter": 500.0}]


# == dispatch and options ============================================================

def test_import_layout_dispatches_by_suffix(tmp_path):
    svg_path = write_svg(tmp_path, '<circle cx="10" cy="10" r="2"/>', name="A.SVG")
    assert import_layout(svg_path, scale=2.0, rod_diameter=None, cell=None)["area"] == [2000.0, 1000.0]
    gds_path = _gds_with(tmp_path, gdstk.ellipse((5, 5), 0.1, layer=1))
    assert import_layout(gds_path, scale=None)["target"][0]["kind"] == "particle"
    doc, msp = dxf_doc()
    msp.add_circle((1, 1), 0.1)
    assert import_layout(save_dxf(tmp_path, doc), area=(5000, 5000))["area"] == [5000.0, 5000.0]


@pytest.mark.parametrize("name, options, line", [
    ("chip.svg", {"rod_diameter": 10}, "{p}: --rod-diameter: does not apply to SVG files "
                                       "(options for SVG: --scale, --keepout-class, --marks-layer)"),
    ("chip.gds", {"scale": 2}, "{p}: --scale: does not apply to GDS files (options for GDS: --cell, --area, "
                               "--particle-layer, --rod-layer, --keepout-layer, --area-layer, --marks-layer)"),
    ("chip.dxf", {"cell": "TOP"}, "{p}: --cell: does not apply to DXF files "
                                  "(options for DXF: --scale, --rod-diameter, --area, --marks-layer)"),
    ("chip.dxf", {"keepout_class": "x"}, "{p}: --keepout-class: does not apply to DXF files "
                                         "(options for DXF: --scale, --rod-diameter, --area, --marks-layer)"),
    ("chip.oas", {}, "{p}: unknown layout file type '.oas'; expected one of .dxf, .gds, .gds2, .gdsii, .svg"),
    ("chip", {}, "{p}: unknown layout file type '(none)'; expected one of .dxf, .gds, .gds2, .gdsii, .svg"),
])
def test_import_layout_rejects_options_that_do_not_apply(tmp_path, name, options, line):
    path = tmp_path / name
    path.write_text("irrelevant: refused before reading")
    with pytest.raises(InputError) as exc:
        import_layout(path, **options)
    assert error_line(exc) == line.format(p=path)


@pytest.mark.parametrize("options, line", [
    ({"scale": -1}, "--scale: must be positive, got -1"),
    ({"scale": 0}, "--scale: must be positive, got 0"),
    ({"scale": float("nan")}, "--scale: must be finite, got nan"),
    ({"scale": "2"}, "--scale: must be a number, got a string '2'"),
    ({"keepout_class": " "}, "--keepout-class: must be a non-empty name, got ' '"),
])
def test_option_values_are_checked(tmp_path, options, line):
    path = write_svg(tmp_path, '<circle cx="10" cy="10" r="2"/>')
    with pytest.raises(InputError) as exc:
        import_layout(path, **options)
    assert error_line(exc) == line


def test_dxf_option_values_are_checked(tmp_path):
    doc, msp = dxf_doc()
    msp.add_line((0, 0), (1, 0))
    path = save_dxf(tmp_path, doc)
    with pytest.raises(InputError, match=r"^--rod-diameter: must be positive, got -3$"):
        import_dxf(path, rod_diameter=-3)
    with pytest.raises(InputError, match=r"^--area: must be two numbers W H"):
        import_dxf(path, area=(1, 2, 3))
    with pytest.raises(InputError, match=r"^--area: must be positive, got 0$"):
        import_dxf(path, area=(1, 0))
