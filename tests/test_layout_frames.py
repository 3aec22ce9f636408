"""Layouts and scans in their frames (issue 17): marks from CAD drawings (--marks-layer),
implausible units, the environment's origin, and a layout that a random scene can fill."""

from __future__ import annotations

import json
import math

import ezdxf
import gdstk
import numpy as np
import pytest

from nanoasm.bodies import Body
from nanoasm.cad.importers import import_layout
from nanoasm.cad.layout import layout_from_dict, load_layout
from nanoasm.cli import main
from nanoasm.dryrun import dry_run
from nanoasm.errors import InputError
from nanoasm.instrument import HeightImage
from nanoasm.planner import PlanOptions
from nanoasm.world.environment import environment_from_dict, load_environment
from nanoasm.world.identify import identify
from nanoasm.world.render import make_surface, render_scan
from nanoasm.world.scene import load_scene

RECT = [(100, 100), (400, 100), (400, 250), (100, 250)]


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("nanoasm: error: ") and "Traceback" not in err[0], err
    return err[0]


# -- marks from CAD drawings ---------------------------------------------------------

def test_svg_marks_by_class_or_group(tmp_path):
    path = tmp_path / "chip.svg"
    path.write_text('<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 1000 1000">'
                    '<circle cx="700" cy="700" r="45"/>'
                    '<g id="marks-layer"><rect x="100" y="100" width="300" height="150"/></g>'
                    '<polygon class="align" points="600,100 900,100 900,200"/>'
                    '<rect class="keepout" x="100" y="600" width="100" height="100"/></svg>')
    doc = import_layout(path, marks_layer="marks")
    assert [m["polygon"] for m in doc["mark"]] == [[[100, 900], [400, 900], [400, 750], [100, 750]]]
    assert len(doc["keepout"]) == 1
    assert len(import_layout(path, marks_layer="align")["mark"]) == 1
    assert "mark" not in import_layout(path)                       # none unless asked for
    layout = layout_from_dict(import_layout(path, marks_layer="marks"), str(path))
    assert len(layout.marks) == 1 and len(layout.regions) == 2


def test_gds_marks_on_a_layer(tmp_path):
    lib = gdstk.Library(unit=1e-9, precision=1e-12)
    top = lib.new_cell("TOP")
    top.add(gdstk.rectangle((0, 0), (1000, 1000), layer=0))
    top.add(gdstk.ellipse((700, 700), 45, tolerance=0.5, layer=1))
    top.add(gdstk.Polygon(RECT, layer=7, datatype=2))
    path = tmp_path / "chip.gds"
    lib.write_gds(str(path))
    doc = import_layout(path, marks_layer="7/2")
    assert sorted(map(tuple, doc["mark"][0]["polygon"])) == sorted(RECT)
    with pytest.raises(InputError, match="--marks-layer: is the same layer 3/0 as --keepout-layer"):
        import_layout(path, marks_layer="3/0")


def test_dxf_marks_on_a_layer(tmp_path):
    doc = ezdxf.new("R2010")
    doc.header["$INSUNITS"] = 12                                    # nm
    msp = doc.modelspace()
    msp.add_lwpolyline([(0, 0), (1000, 0), (1000, 1000), (0, 1000)], close=True, dxfattribs={"layer": "AREA"})
    msp.add_circle((700, 700), 45)
    msp.add_lwpolyline(RECT, close=True, dxfattribs={"layer": "Marks"})
    msp.add_circle((200, 700), 30, dxfattribs={"layer": "Marks"})   # no corners: not a mark
    path = tmp_path / "chip.dxf"
    doc.saveas(path)
    notes: list[str] = []
    out = import_layout(path, marks_layer="MARKS", warnings=notes)
    assert [list(map(tuple, m["polygon"])) for m in out["mark"]] == [RECT] and "keepout" not in out
    assert any("CIRCLE on the marks layer" in n for n in notes)
    assert len(import_layout(path)["keepout"]) == 1                  # without the option: a keep-out


def test_layout_convert_takes_marks_layer(tmp_path, capsys):
    svg = tmp_path / "chip.svg"
    svg.write_text('<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 1000 1000"><circle cx="700" cy="700" '
                   'r="45"/><rect class="mark" x="100" y="100" width="300" height="150"/></svg>')
    out = tmp_path / "chip.toml"
    assert main(["layout", "convert", str(svg), "-o", str(out), "--marks-layer", "mark"]) == 0
    assert "1 mark(s)" in capsys.readouterr().out and len(load_layout(out).marks) == 1


def test_a_target_on_a_mark_is_refused():
    doc = {"format": "nanoasm.layout/1", "area": [1000, 1000], "target": [{"kind": "particle", "at": [200, 150],
                                                                           "diameter": 50}],
           "mark": [{"polygon": [list(p) for p in RECT]}]}
    with pytest.raises(InputError, match=r"^l: target\[1\]: target 't1' overlaps mark\[1\]$"):
        layout_from_dict(doc, "l")


# -- units and origins ---------------------------------------------------------------

def test_a_dxf_in_decimetres_is_refused_with_a_hint(tmp_path, capsys):
    doc = ezdxf.new("R2010")
    doc.header["$INSUNITS"] = 14                                    # decimetres
    msp = doc.modelspace()
    msp.add_lwpolyline([(0, 0), (3, 0), (3, 3), (0, 3)], close=True, dxfattribs={"layer": "AREA"})
    msp.add_circle((1, 1), 1e-7)
    path = tmp_path / "chip.dxf"
    doc.saveas(path)
    assert main(["layout", "check", str(path)]) == 1
    line = one_line(capsys)
    assert line == (f"nanoasm: error: {path}: area: working area 3e+08 x 3e+08 nm (300 mm a side) is no AFM's: "
                    "are the drawing's units right? ($INSUNITS = 14, 1e+08 nm per drawing unit (--scale "
                    "overrides it))")


def test_a_layout_area_beyond_a_millimetre_names_the_units():
    doc = {"format": "nanoasm.layout/1", "area": [3e6, 3e6], "target": [{"kind": "particle", "at": [50, 50],
                                                                         "diameter": 50}]}
    with pytest.raises(InputError, match=r"3 mm is no AFM's working area: are the units right"):
        layout_from_dict(doc, "l")


def test_a_huge_scan_warns_about_its_units(tmp_path, capsys):
    scan = tmp_path / "scan.npy"
    np.save(scan, np.zeros((64, 64)))
    assert main(["identify", str(scan), "--pixel-size", "50000", "-o", str(tmp_path / "env.json")]) == 0
    err = capsys.readouterr().err
    assert "the image spans 3.2e+06 x 3.2e+06 nm, more than 1 mm: are its units right" in err


def test_identify_records_an_absolute_scans_origin(tmp_path, capsys):
    rng = np.random.default_rng(4)
    img = render_scan(make_surface([Body("p", "particle", (700.0, 300.0), 90.0)], [], (1000.0, 1000.0), rng=rng),
                      10.0, rng=rng)
    # an .xyz list in a stage's absolute coordinates (nm), as the scan was
    rows = [f"{22000 + (j + 0.5) * 10:.1f} {30000 + (i + 0.5) * 10:.1f} {img.height[i, j]:.4f}"
            for i in range(img.height.shape[0]) for j in range(img.height.shape[1])]
    xyz = tmp_path / "abs.xyz"
    xyz.write_text("# Units: nm\n" + "\n".join(rows))
    out = tmp_path / "env.json"
    assert main(["identify", str(xyz), "-o", str(out)]) == 0
    env = load_environment(out)
    assert env.origin == pytest.approx((22000.0, 30000.0), abs=1.0)
    (o,) = env.objects
    assert o.at == pytest.approx((700.0, 300.0), abs=2.0)            # in the area, from the scan's corner
    assert identify(HeightImage(img.height, 10.0)).to_dict().keys() == {"format", "area", "objects",
                                                                         "obstacles"}     # (0, 0): no key


def test_env_origin_is_optional_and_checked():
    base = {"format": "nanoasm.env/1", "area": [100, 100], "objects": [], "obstacles": []}
    assert environment_from_dict(base).origin == (0.0, 0.0)
    assert environment_from_dict({**base, "origin": [5, -7]}).origin == (5.0, -7.0)
    with pytest.raises(InputError, match=r"^e: origin: x must be finite"):
        environment_from_dict({**base, "origin": [float("nan"), 0]}, "e")


# -- a layout for a random scene -----------------------------------------------------

def test_scene_random_writes_a_layout_it_can_fill(tmp_path, capsys):
    scene, layout = tmp_path / "s.toml", tmp_path / "l.toml"
    args = ["scene", "random", "--particles", "8", "--rods", "1", "--obstacles", "1", "--area", "3000", "3000",
            "--rod-length", "300", "400", "--seed", "2", "-o", str(scene)]
    assert main([*args, "--layout", str(layout), "--slots", "3"]) == 0
    out = capsys.readouterr().out
    assert f"{layout}: written: 'random-2': 3000 x 3000 nm, 3 particle slot(s), 0 rod slot(s), 1 keep-out(s)" in out
    sc, lay = load_scene(scene), load_layout(layout)
    particles = sorted(o.diameter for o in sc.objects if o.kind == "particle")
    assert all(round(t.diameter, 1) in {round(d, 1) for d in particles} for t in lay.targets)
    out = dry_run(sc, lay, seed=2, plan_options=PlanOptions(seed=2))
    assert out.truly_filled == ("s1", "s2", "s3")
    # rods come after the particles
    assert main([*args, "--layout", str(layout), "--slots", "9"]) == 0
    assert sum(t.kind == "rod" for t in load_layout(layout).targets) == 1
    capsys.readouterr()
    assert main([*args, "--layout", str(layout), "--slots", "10"]) == 1
    assert "--slots: the scene has 9 object(s) a slot can take (8 particle(s), 1 rod(s)" in one_line(capsys)
    assert main([*args, "--slots", "3"]) == 1
    assert "--slots: goes with --layout" in one_line(capsys)
    assert main([*args, "--layout", str(scene), "--slots", "3"]) == 1
    assert "is also an input (-o)" in one_line(capsys)


def test_the_same_scene_gives_the_same_layout(tmp_path):
    paths = []
    for k in range(2):
        s, lay = tmp_path / f"s{k}.json", tmp_path / f"l{k}.json"
        assert main(["scene", "random", "--particles", "30", "--seed", "7", "-o", str(s), "--layout", str(lay),
                     "--slots", "6"]) == 0
        paths.append(lay)
    a, b = (json.loads(p.read_text()) for p in paths)
    assert a == b
    slots = [t for t in load_layout(paths[0]).targets]
    gaps = [math.dist(p.at, q.at) - p.radius - q.radius for i, p in enumerate(slots) for q in slots[i + 1:]]
    assert min(gaps) >= 60.0 - 1e-6
