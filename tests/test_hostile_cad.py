"""Hostile CAD files (issue 15): cyclic references, huge arrays, deep nesting, fan-outs
and huge arcs end in one error line naming the file, exit 1, in bounded time and memory.

Every hostile file is generated small here (raw GDSII records, ezdxf, SVG text) and run
through ``nanoasm layout check`` in a subprocess limited to 1 GiB of address space and a
10 s timeout, so a segfault, a hang or a memory blow-up fails the test instead of killing
pytest. Modest arrays and ``<use>`` still import correctly.
"""

from __future__ import annotations

import math
import resource
import struct
import subprocess
import sys
import time

import ezdxf
import gdstk
import pytest
from nanoasm.cad import dxf as dxf_mod
from nanoasm.cad import gds as gds_mod
from nanoasm.cad import importers
from nanoasm.cad import svg as svg_mod
from nanoasm.cad.importers import import_layout
from nanoasm.cli import main

from nanoasm.errors import InputError

TIME_LIMIT = 10.0          # s
MEMORY_LIMIT = 1 << 30     # bytes of address space


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def check_refused(path, *fragments: str, options: tuple[str, ...] = ()) -> str:
    """Run ``nanoasm layout check`` on ``path`` in a limited subprocess; return its one
    error line after checking exit code, line count, file name, time and fragments."""
    start = time.monotonic()
    try:
        proc = subprocess.run([sys.executable, "-m", "nanoasm.cli", "layout", "check", str(path), *options],
                              capture_output=True, text=True, timeout=TIME_LIMIT, cwd=path.parent,
                              preexec_fn=_limit_memory)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{path.name}: no answer within {TIME_LIMIT} s")
    elapsed = time.monotonic() - start
    lines = proc.stderr.splitlines()
    assert proc.returncode == 1, f"exit {proc.returncode}: {proc.stderr[-2000:]}"
    assert len(lines) == 1, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    line = lines[0]
    assert line.startswith(f"nanoasm: error: {path}: "), line
    for fragment in fragments:
        assert fragment in line, line
    assert elapsed < TIME_LIMIT
    return line


# == GDSII, written record by record (gdstk would not build some of these) ============

def _real8(v: float) -> bytes:
    """GDSII 8-byte real: sign, excess-64 base-16 exponent, 56-bit mantissa."""
    if v == 0:
        return bytes(8)
    sign, v, exp = (0x80 if v < 0 else 0), abs(v), 64
    while v >= 1:
        v, exp = v / 16, exp + 1
    while v < 1 / 16:
        v, exp = v * 16, exp - 1
    return bytes([sign | exp]) + round(v * 2 ** 56).to_bytes(7, "big")


def _record(rtype: int, dtype: int, data: bytes = b"") -> bytes:
    return struct.pack(">HBB", 4 + len(data), rtype, dtype) + data


def _ints(fmt: str, *values: int) -> bytes:
    return struct.pack(f">{len(values)}{fmt}", *values)


def _name(text: str) -> bytes:
    raw = text.encode()
    return raw + b"\0" * (len(raw) % 2)


def gds_library(cells: list[tuple[str, list[bytes]]]) -> bytes:
    """A library (1 nm database unit) of ``(name, elements)`` cells."""
    out = (_record(0x00, 2, _ints("h", 600)) + _record(0x01, 2, _ints("h", *[0] * 12))
           + _record(0x02, 6, _name("LIB")) + _record(0x03, 5, _real8(1e-3) + _real8(1e-9)))
    for name, elements in cells:
        out += (_record(0x05, 2, _ints("h", *[0] * 12)) + _record(0x06, 6, _name(name))
                + b"".join(elements) + _record(0x07, 0))
    return out + _record(0x04, 0)


def gds_polygon(layer: int, points: list[tuple[int, int]]) -> bytes:
    xy = [c for p in [*points, points[0]] for c in p]
    return (_record(0x08, 0) + _record(0x0D, 2, _ints("h", layer)) + _record(0x0E, 2, _ints("h", 0))
            + _record(0x10, 3, _ints("i", *xy)) + _record(0x11, 0))


def gds_sref(cell: str) -> bytes:
    return (_record(0x0A, 0) + _record(0x12, 6, _name(cell)) + _record(0x10, 3, _ints("i", 0, 0))
            + _record(0x11, 0))


def gds_aref(cell: str, columns: int, rows: int, pitch: int = 200) -> bytes:
    return (_record(0x0B, 0) + _record(0x12, 6, _name(cell)) + _record(0x13, 2, _ints("h", columns, rows))
            + _record(0x10, 3, _ints("i", 0, 0, columns * pitch, 0, 0, rows * pitch)) + _record(0x11, 0))


def gds_circle(cx: int = 0, cy: int = 0, r: int = 50, n: int = 16) -> bytes:
    return gds_polygon(1, [(round(cx + r * math.cos(2 * math.pi * k / n)),
                            round(cy + r * math.sin(2 * math.pi * k / n))) for k in range(n)])


def write(tmp_path, name: str, data: bytes | str):
    path = tmp_path / name
    if isinstance(data, str):
        path.write_text(data)
    else:
        path.write_bytes(data)
    return path


def test_gds_cyclic_reference(tmp_path):
    path = write(tmp_path, "cyclic.gds", gds_library([
        ("TOP", [gds_sref("A")]), ("A", [gds_circle(), gds_sref("B")]), ("B", [gds_sref("A")])]))
    assert path.stat().st_size < 1000
    check_refused(path, "cell A", "references itself (A > B > A)", options=("--area", "1000", "1000"))


def test_gds_cell_referencing_itself_chosen_with_cell(tmp_path):
    path = write(tmp_path, "self.gds", gds_library([("TOP", [gds_circle(), gds_sref("TOP")])]))
    check_refused(path, "cell TOP", "references itself (TOP > TOP)",
                  options=("--cell", "TOP", "--area", "1000", "1000"))


def test_gds_huge_aref(tmp_path):
    path = write(tmp_path, "aref.gds", gds_library([("TOP", [gds_aref("P", 32767, 32767)]),
                                                    ("P", [gds_circle()])]))
    assert path.stat().st_size < 600
    check_refused(path, "cell TOP", "32767 x 32767", f"{gds_mod.MAX_INSTANCES} instances",
                  options=("--area", "1000", "1000"))


def test_gds_exponential_fan_out(tmp_path):
    """30 levels of 2-element arrays: 2^30 placements from a 3 KB file."""
    cells = [(f"C{i}", [gds_aref(f"C{i + 1}", 2, 1)]) for i in range(30)]
    cells.append(("C30", [gds_polygon(7, [(0, 0), (9, 0), (0, 9)])]))
    path = write(tmp_path, "fanout.gds", gds_library(cells))
    check_refused(path, f"more than the {gds_mod.MAX_INSTANCES} instances",
                  options=("--area", "1000", "1000"))


def test_gds_deep_nesting(tmp_path):
    n = 3 * gds_mod.MAX_DEPTH
    cells = [(f"D{i}", [gds_sref(f"D{i + 1}")]) for i in range(n)] + [(f"D{n}", [gds_circle()])]
    path = write(tmp_path, "deep.gds", gds_library(cells))
    check_refused(path, "cell D0", f"nested more than {gds_mod.MAX_DEPTH} deep",
                  options=("--area", "1000", "1000"))


def test_gds_nesting_at_the_limit_imports(tmp_path):
    n = gds_mod.MAX_DEPTH
    cells = [(f"D{i}", [gds_sref(f"D{i + 1}")]) for i in range(n)] + [(f"D{n}", [gds_circle(500, 500)])]
    doc = import_layout(write(tmp_path, "limit.gds", gds_library(cells)), area=(1000, 1000))
    assert [t["at"] for t in doc["target"]] == [[500.0, 500.0]]
    cells.insert(0, ("TOP", [gds_sref("D0")]))
    with pytest.raises(InputError, match=f"nested more than {n} deep"):
        import_layout(write(tmp_path, "over.gds", gds_library(cells)), area=(1000, 1000))


def test_gds_round_path_ends_count_as_drawn(tmp_path):
    """A round-ended path 2 mm wide on the keep-out layer has 4 spine vertices but gdstk
    draws its ends to 1 nm (~70 000 points); 20 copies pass the vertex budget. Refused
    from the estimate before anything is flattened."""
    path_element = (_record(0x09, 0) + _record(0x0D, 2, _ints("h", 3)) + _record(0x0E, 2, _ints("h", 0))
                    + _record(0x21, 2, _ints("h", 1)) + _record(0x0F, 3, _ints("i", 2 * 10 ** 9))
                    + _record(0x10, 3, _ints("i", 0, 0, 10, 0)) + _record(0x11, 0))
    path = write(tmp_path, "round.gds", gds_library([("TOP", [gds_aref("WIDE", 20, 1)]),
                                                     ("WIDE", [path_element])]))
    check_refused(path, "cell TOP", "its array of WIDE: 20 x 1", f"{gds_mod.MAX_VERTICES} vertices",
                  options=("--area", "1000", "1000"))


def test_gds_modest_aref_still_imports(tmp_path):
    lib = gdstk.Library(unit=1e-9)
    dot = lib.new_cell("DOT")
    dot.add(gdstk.ellipse((0, 0), 25, tolerance=0.01, layer=1))
    top = lib.new_cell("TOP")
    top.add(gdstk.Reference(dot, (100, 100), columns=20, rows=10, spacing=(200, 300)))
    top.add(gdstk.rectangle((0, 0), (5000, 4000), layer=0))
    top.add(gdstk.Label("note", (10, 10)))
    path = tmp_path / "array.gds"
    lib.write_gds(str(path))
    warnings: list[str] = []
    doc = import_layout(path, warnings=warnings)
    ats = sorted(tuple(t["at"]) for t in doc["target"])
    assert len(ats) == 200 and ats[0] == (100.0, 100.0) and ats[-1] == (3900.0, 2800.0)
    assert all(abs(t["diameter"] - 50) < 0.5 for t in doc["target"])
    assert warnings == [f"{path}: ignored 1 text label(s)"]
    assert main(["layout", "check", str(path)]) == 0


# == DXF =============================================================================

def dxf_doc():
    doc = ezdxf.new("R2010")
    doc.header["$INSUNITS"] = 12  # nm
    return doc


def test_dxf_huge_minsert(tmp_path):
    doc = dxf_doc()
    doc.blocks.new("P").add_circle((0, 0), 10)
    doc.modelspace().add_blockref("P", (0, 0)).grid(size=(30000, 30000), spacing=(30, 30))
    doc.saveas(tmp_path / "minsert.dxf")
    check_refused(tmp_path / "minsert.dxf", "INSERT", "block P (30000 x 30000 MINSERT)",
                  f"{dxf_mod.MAX_INSTANCES} entities", options=("--area", "1000", "1000"))


def test_dxf_minsert_with_one_zero_spacing(tmp_path):
    """ezdxf's MINSERT loop runs rows x columns times even when a spacing is 0."""
    doc = dxf_doc()
    doc.blocks.new("P").add_circle((0, 0), 10)
    ins = doc.modelspace().add_blockref("P", (0, 0))
    ins.grid(size=(30000, 30000), spacing=(30, 30))
    ins.dxf.column_spacing = 0
    doc.saveas(tmp_path / "zero.dxf")
    check_refused(tmp_path / "zero.dxf", "30000 x 30000 MINSERT", options=("--area", "1000", "1000"))


def test_dxf_nested_blocks_fan_out(tmp_path):
    """8 levels of 10 inserts each: 10^8 entities."""
    doc = dxf_doc()
    doc.blocks.new("L0").add_circle((0, 0), 10)
    for i in range(1, 9):
        block = doc.blocks.new(f"L{i}")
        for k in range(10):
            block.add_blockref(f"L{i - 1}", (k * 100, 0))
    doc.modelspace().add_blockref("L8", (0, 0))
    doc.saveas(tmp_path / "nested.dxf")
    check_refused(tmp_path / "nested.dxf", "INSERT", f"{dxf_mod.MAX_INSTANCES} entities",
                  options=("--area", "1000", "1000"))


def test_dxf_block_cycle(tmp_path):
    doc = dxf_doc()
    a, b = doc.blocks.new("A"), doc.blocks.new("B")
    a.add_circle((0, 0), 5)
    a.add_blockref("B", (0, 0))
    b.add_blockref("A", (10, 0))
    doc.modelspace().add_blockref("A", (0, 0))
    doc.saveas(tmp_path / "cycle.dxf")
    check_refused(tmp_path / "cycle.dxf", "INSERT", "block A is inserted in itself (A > B > A)",
                  options=("--area", "1000", "1000"))


def _dxf_chain(path, levels: int) -> None:
    doc = dxf_doc()
    doc.blocks.new("B0").add_circle((500, 500), 10)
    for i in range(1, levels):
        doc.blocks.new(f"B{i}").add_blockref(f"B{i - 1}", (0, 0))
    doc.modelspace().add_blockref(f"B{levels - 1}", (0, 0))
    doc.saveas(path)


def test_dxf_deep_block_nesting(tmp_path):
    _dxf_chain(tmp_path / "deep.dxf", 3 * dxf_mod.MAX_DEPTH)
    check_refused(tmp_path / "deep.dxf", "INSERT", f"nested more than {dxf_mod.MAX_DEPTH} deep",
                  options=("--area", "1000", "1000"))
    _dxf_chain(tmp_path / "limit.dxf", dxf_mod.MAX_DEPTH)
    doc = import_layout(tmp_path / "limit.dxf", area=(1000, 1000))
    assert [t["at"] for t in doc["target"]] == [[500.0, 500.0]]
    _dxf_chain(tmp_path / "over.dxf", dxf_mod.MAX_DEPTH + 1)
    with pytest.raises(InputError, match="nested more than"):
        import_layout(tmp_path / "over.dxf", area=(1000, 1000))


def test_dxf_huge_radius_bulge(tmp_path):
    doc = dxf_doc()
    msp = doc.modelspace()
    msp.add_lwpolyline([(0, 0, 0, 0, 0.999999), (1e15, 0, 0, 0, 0.999999), (1e15, 1e15)],
                       format="xyseb", close=True)
    msp.add_circle((0, 0), 10)
    doc.saveas(tmp_path / "bulge.dxf")
    check_refused(tmp_path / "bulge.dxf", "LWPOLYLINE", f"{dxf_mod.MAX_ARC_POINTS} arc points",
                  options=("--area", "1000", "1000"))


def test_dxf_modest_minsert_and_round_keepout_still_import(tmp_path):
    doc = dxf_doc()
    doc.blocks.new("P").add_circle((0, 0), 10)
    msp = doc.modelspace()
    # 4 rows 200 apart, 3 columns 100 apart
    msp.add_blockref("P", (100, 100)).grid(size=(4, 3), spacing=(200, 100))
    msp.add_lwpolyline([(0, 0), (2000, 0), (2000, 1000), (0, 1000)], close=True, dxfattribs={"layer": "AREA"})
    b = math.tan(math.pi / 8)  # four quarter arcs: a circle of radius 50 nm
    msp.add_lwpolyline([(1550, 500, 0, 0, b), (1500, 550, 0, 0, b), (1450, 500, 0, 0, b),
                        (1500, 450, 0, 0, b)], format="xyseb", close=True)
    doc.saveas(tmp_path / "array.dxf")
    out = import_layout(tmp_path / "array.dxf")
    ats = sorted(tuple(t["at"]) for t in out["target"])
    assert len(ats) == 12 and ats[0] == (100.0, 100.0) and ats[-1] == (300.0, 700.0)
    (keepout,) = out["keepout"]
    assert len(keepout["polygon"]) > 16
    assert all(abs(math.hypot(x - 1500, y - 500) - 50) < 1.0 for x, y in keepout["polygon"])


# == SVG =============================================================================

SVG_HEAD = ('<svg xmlns="http://www.w3.org/2000/svg" xmlns:xlink="http://www.w3.org/1999/xlink" '
            'viewBox="0 0 1000 1000">\n')


def nested_svg(groups: int) -> str:
    return SVG_HEAD + "<g>" * groups + '<circle cx="5" cy="5" r="1"/>' + "</g>" * groups + "</svg>\n"


def test_svg_deeply_nested_groups(tmp_path):
    n = 100_000
    path = write(tmp_path, "deep.svg", nested_svg(n))
    check_refused(path, f"nested more than {svg_mod.MAX_DEPTH} deep")


def test_svg_nesting_at_the_limit_imports(tmp_path):
    n = svg_mod.MAX_DEPTH - 2   # the root, the groups and the circle
    path = write(tmp_path, "limit.svg", nested_svg(n))
    assert [t["at"] for t in import_layout(path)["target"]] == [[5.0, 995.0]]
    path = write(tmp_path, "over.svg", nested_svg(n + 1))
    with pytest.raises(InputError, match="nested more than"):
        import_layout(path)


def test_svg_use_fan_out(tmp_path):
    body = '<defs><g id="a0"><circle cx="5" cy="5" r="1"/></g>\n'
    for i in range(1, 12):
        uses = "".join(f'<use xlink:href="#a{i - 1}" x="{k}"/>' for k in range(10))
        body += f'<g id="a{i}">{uses}</g>\n'
    body += '</defs><use xlink:href="#a11"/>\n'
    path = write(tmp_path, "fanout.svg", SVG_HEAD + body + "</svg>\n")
    assert path.stat().st_size < 4000
    check_refused(path, f"{svg_mod.MAX_INSTANCES} elements")


@pytest.mark.parametrize("body, fragment", [
    ('<g id="a"><circle cx="5" cy="5" r="1"/><use xlink:href="#b"/></g><g id="b"><use xlink:href="#a"/></g>',
     "use[2]: <use> refers to g#a, which leads back to this <use> (a reference cycle)"),
    ('<use id="u" href="#u"/><circle cx="5" cy="5" r="1"/>', "use#u: <use> refers to itself"),
    ('<circle cx="5" cy="5" r="1"/><use href="#root"/>',
     "use[1]: <use> refers to svg#root, which leads back"),
], ids=["two-groups", "itself", "root"])
def test_svg_use_cycles(tmp_path, body, fragment):
    path = write(tmp_path, "cycle.svg", SVG_HEAD.replace("viewBox", 'id="root" viewBox') + body + "</svg>\n")
    check_refused(path, fragment)


def test_svg_modest_use_still_imports(tmp_path):
    body = ('<defs><g id="cell"><circle cx="0" cy="0" r="10"/>'
            '<line x1="20" y1="0" x2="60" y2="0" stroke-width="8"/></g>'
            '<g id="row">' + "".join(f'<use href="#cell" x="{100 * k}"/>' for k in range(5)) + "</g></defs>"
            + "".join(f'<use xlink:href="#row" x="100" y="{100 + 200 * k}"/>' for k in range(4)))
    path = write(tmp_path, "uses.svg", SVG_HEAD + body + "</svg>\n")
    doc = import_layout(path)
    particles = sorted(tuple(t["at"]) for t in doc["target"] if t["kind"] == "particle")
    rods = [t for t in doc["target"] if t["kind"] == "rod"]
    assert len(particles) == 20 and len(rods) == 20
    assert particles[0] == (100.0, 300.0) and particles[-1] == (500.0, 900.0)
    assert all(r["length"] == 40.0 and r["diameter"] == 8.0 for r in rods)


# == every importer ===================================================================

def test_targets_and_keepouts_are_budgeted(tmp_path, monkeypatch):
    monkeypatch.setattr(importers, "MAX_ELEMENTS", 5)
    circles = "".join(f'<circle cx="{20 * k + 10}" cy="10" r="5"/>' for k in range(6))
    path = write(tmp_path, "many.svg", SVG_HEAD + circles + "</svg>\n")
    with pytest.raises(InputError, match="more than 5 targets and keep-outs"):
        import_layout(path)


@pytest.mark.parametrize("module, names", [
    (gds_mod, ("MAX_DEPTH", "MAX_INSTANCES", "MAX_VERTICES")),
    (dxf_mod, ("MAX_DEPTH", "MAX_INSTANCES", "MAX_ARC_POINTS")),
    (svg_mod, ("MAX_DEPTH", "MAX_INSTANCES")),
    (importers, ("MAX_ELEMENTS",)),
])
def test_limits_are_named_positive_constants(module, names):
    for name in names:
        value = getattr(module, name)
        assert isinstance(value, int) and value > 0
