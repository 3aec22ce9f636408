"""Layout v1: valid files load and round-trip; every class of mistake gets one clear line."""

from __future__ import annotations

import copy
import json
import math
import tomllib

import pytest

from nanoasm.cad.layout import layout_from_dict, load_layout
from nanoasm.errors import InputError
from nanoasm.examples import path as example

from doc_edits import DELETE


def base() -> dict:
    return {
        "format": "nanoasm.layout/1",
        "name": "t",
        "area": [5000, 5000],
        "target": [
            {"id": "p1", "kind": "particle", "at": [1000, 1000], "diameter": 100},
            {"id": "r1", "kind": "rod", "at": [2500, 2500], "angle": 30, "length": 1300, "diameter": 100},
        ],
        "keepout": [{"polygon": [[0, 4000], [800, 4000], [800, 4400], [0, 4400]]}],
    }


def reject(data: dict, *fragments: str) -> str:
    with pytest.raises(InputError) as info:
        layout_from_dict(data, "lay.toml")
    line = str(info.value)
    assert "\n" not in line
    assert line.startswith("lay.toml: ")
    for f in fragments:
        assert f in line, line
    return line


def test_bundled_example_loads():
    layout = load_layout(example("bowtie.toml"))
    assert layout.name == "bowtie"
    assert len(layout.targets) == 7 and len(layout.keepouts) == 2


def test_valid_layout_defaults():
    lay = layout_from_dict(base(), "lay.toml")
    assert lay.tolerance.position == 20 and lay.tolerance.angle == 3 and lay.tolerance.size == 0.25
    assert lay.target("r1").length == 1300
    ids = [t.id for t in layout_from_dict({**base(), "target": [
        {"kind": "particle", "at": [100, 100], "diameter": 10},
        {"kind": "particle", "at": [300, 100], "diameter": 10}]}).targets]
    assert ids == ["t1", "t2"]


def test_round_trip_toml_and_json(tmp_path):
    lay = layout_from_dict(base())
    for name in ("a.toml", "a.json"):
        lay.save(tmp_path / name)
        assert load_layout(tmp_path / name) == lay
    assert layout_from_dict(tomllib.loads(lay.dumps_toml())) == lay
    assert layout_from_dict(json.loads(lay.dumps_json())) == lay


def mutate(path: str, value) -> dict:
    """Set (or delete, for value=DELETE) a key given as 'target.1.diameter' (0-based)."""
    data = copy.deepcopy(base())
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    node = data
    for k in keys[:-1]:
        node = node[k]
    if value is DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return data


CASES = [
    # (path, value, key path in message, problem fragment)
    ("format", DELETE, "format", "missing required key"),
    ("format", "nanoasm.layout/2", "format", "unsupported version"),
    ("format", "nanoasm.scene/1", "format", "expected 'nanoasm.layout/1'"),
    ("format", "svg", "format", "unknown format"),
    ("format", 1, "format", "must be the string"),
    ("area", DELETE, "area", "missing required key"),
    ("area", [5000], "area", "two numbers"),
    ("area", [5000, 0], "area", "height must be positive"),
    ("area", [-1, 100], "area", "width must be positive"),
    ("area", [5000, math.nan], "area", "must be finite"),
    ("area", [math.inf, 5000], "area", "must be finite"),
    ("area", "5000x5000", "area", "must be an array"),
    ("area", [True, 5000], "area", "must be a number"),
    ("name", 3, "name", "must be a string"),
    ("name", "", "name", "must not be empty"),
    ("colour", "red", "colour", "unknown key"),
    ("target.0.diamter", 100, "target[1].diamter", "did you mean 'diameter'"),
    ("target.0.diameter", DELETE, "target[1].diameter", "missing required key"),
    ("target.0.diameter", -5, "target[1].diameter", "must be positive"),
    ("target.0.diameter", 0, "target[1].diameter", "must be positive"),
    ("target.0.diameter", "100", "target[1].diameter", "must be a number, got a string"),
    ("target.0.diameter", math.nan, "target[1].diameter", "must be finite"),
    ("target.0.at", [1000, math.inf], "target[1].at", "y must be finite"),
    ("target.0.at", [1000], "target[1].at", "two numbers"),
    ("target.0.kind", "tube", "target[1].kind", "must be one of"),
    ("target.0.kind", DELETE, "target[1].kind", "missing required key"),
    ("target.0.angle", 10, "target[1].angle", "unknown key for a particle"),
    ("target.1.angle", DELETE, "target[2].angle", "missing required key for a rod"),
    ("target.1.length", 50, "target[2].length", "at least the diameter"),
    ("target.1.length", -1, "target[2].length", "must be positive"),
    ("target.1.id", "p1", "target[2].id", "duplicate id 'p1'"),
    ("target.1.id", 7, "target[2].id", "must be a string"),
    ("target.0.at", [30, 1000], "target[1]", "outside the area"),
    ("target.0.at", [1000, 4970], "target[1]", "outside the area"),
    ("target.0.at", [2500, 2600], "target[2]", "overlaps target 'p1'"),
    ("target.0.at", [400, 4100], "target[1]", "overlaps keepout[1]"),
    ("target", [], "target", "at least one"),
    ("target", {"kind": "particle"}, "target", "array of tables"),
    ("target.0", "p1", "target[1]", "must be a table"),
    ("tolerance", {"position": 0}, "tolerance.position", "must be positive"),
    ("tolerance", {"angel": 1}, "tolerance.angel", "did you mean 'angle'"),
    ("tolerance", {"size": 2}, "tolerance.size", "at most 1"),
    ("tolerance", 5, "tolerance", "must be a table"),
    ("keepout.0.polygon", [[0, 0], [10, 10]], "keepout[1].polygon", "at least 3"),
    ("keepout.0.polygon", [[0, 0], [100, 100], [100, 0], [0, 100]], "keepout[1].polygon", "intersects itself"),
    ("keepout.0.polygon", [[0, 0], [100, 100], [200, 200]], "keepout[1].polygon", "zero area"),
    ("keepout.0.polygon", [[0, 0], [100, "a"], [200, 0]], "keepout[1].polygon[2]", "y must be a number"),
    ("keepout.0.polygon", [[0, 0], [100, 0, 1], [200, 0]], "keepout[1].polygon[2]", "must be a point"),
    ("keepout.0.polygon", DELETE, "keepout[1].polygon", "missing required key"),
    ("keepout.0.shape", "x", "keepout[1].shape", "unknown key"),
]


@pytest.mark.parametrize("path,value,key,problem", CASES, ids=[f"{c[0]}={c[1]!r}"[:40] for c in CASES])
def test_rejections(path, value, key, problem):
    line = reject(mutate(path, value), f": {key}", problem)
    assert line.split(": ")[1].startswith(key), line


def test_touching_targets_and_keepout_boundary_are_allowed():
    data = base()
    data["target"] = [
        {"id": "a", "kind": "particle", "at": [1000, 1000], "diameter": 100},
        {"id": "b", "kind": "particle", "at": [1100, 1000], "diameter": 100},   # touches a
        {"id": "c", "kind": "particle", "at": [400, 3950], "diameter": 100},    # touches the keep-out
        {"id": "d", "kind": "particle", "at": [50, 50], "diameter": 100},       # touches two area edges
    ]
    assert len(layout_from_dict(data).targets) == 4


def test_rods_overlap_as_capsules():
    data = base()
    # two parallel rods 90 nm apart (diameter 100): overlap although the centres are far apart
    data["target"] = [
        {"kind": "rod", "at": [2500, 2500], "angle": 0, "length": 1000, "diameter": 100},
        {"kind": "rod", "at": [2900, 2590], "angle": 0, "length": 1000, "diameter": 100},
    ]
    reject(data, "overlaps target 't1'")
    data["target"][1]["at"] = [2900, 2600]
    layout_from_dict(data)


def test_rod_end_outside_area():
    data = base()
    data["target"] = [{"kind": "rod", "at": [300, 2500], "angle": 0, "length": 800, "diameter": 50}]
    reject(data, "outside the area")
    data["target"][0]["angle"] = 90
    layout_from_dict(data)
