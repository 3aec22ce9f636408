"""Golden files and exact round-trips for layout, environment, plan and report v1."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import pytest
from hypothesis import given, strategies as st

from nanoasm.bodies import Body
from nanoasm.cad.layout import Keepout, Layout, Tolerance, layout_from_dict, load_layout
from nanoasm.errors import InputError
from nanoasm.executor.report import Counts, InstrumentTime, Report, WallTime, load_report, report_from_dict
from nanoasm.planner.plan import Assignment, Expect, Operation, Plan, Unfilled, load_plan, plan_from_dict
from nanoasm.world.environment import EnvObject, EnvObstacle, Environment, environment_from_dict, load_environment

GOLDEN = Path(__file__).parent / "golden"


def test_layout_golden():
    layout = load_layout(GOLDEN / "layout_input.toml")
    assert layout.dumps_toml() == (GOLDEN / "layout_expected.toml").read_text()
    assert layout.target("t1").diameter == 80.0
    assert layout.target("wire-bridge").angle == 90.5


@pytest.mark.parametrize("name,loader", [("env.json", load_environment), ("plan.json", load_plan),
                                         ("report.json", load_report)])
def test_json_golden_files_round_trip_byte_for_byte(name, loader):
    text = (GOLDEN / name).read_text()
    assert loader(GOLDEN / name).dumps() == text


def test_a_report_keeps_the_runs_verdict_and_reads_one_written_before_it():
    from nanoasm.executor.report import report_from_dict

    data = json.loads((GOLDEN / "report.json").read_text())
    (v,) = load_report(GOLDEN / "report.json").slots
    assert (v.target, v.object, v.state, v.error) == ("t1", "o1", "filled", 3.25)
    assert report_from_dict({k: x for k, x in data.items() if k != "slots"}).slots == ()
    with pytest.raises(InputError, match=r"slots\[1\]\.state: must be one of filled, missed, unfilled"):
        report_from_dict({**data, "slots": [{**data["slots"][0], "state": "full"}]}, "r.json")


def test_golden_values():
    env = load_environment(GOLDEN / "env.json")
    assert env.object("o3").kind == "wire" and env.object("o3").edge
    assert env.obstacles[0].height == 25.0
    plan = load_plan(GOLDEN / "plan.json")
    assert plan.operations[0].expect.angle is None and plan.operations[1].target is None
    rep = load_report(GOLDEN / "report.json")
    assert rep.counts == Counts(3, 6, 1, 1) and rep.instrument_time.total == 324.75


# -- hypothesis: random valid documents round-trip exactly ---------------------------

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
coord = st.floats(0, 1e4, allow_nan=False)
name = st.text(st.characters(min_codepoint=33, max_codepoint=0x2FFF, exclude_categories=("Cs", "Cc", "Zs", "Zl", "Zp")),
               min_size=1, max_size=12)


@st.composite
def layouts(draw):
    """Targets on a jittered grid so they never overlap; rods lie along their cell."""
    cols, rows = draw(st.integers(1, 6)), draw(st.integers(1, 6))
    cell = draw(st.floats(200, 2000))
    targets = []
    for k in range(draw(st.integers(1, cols * rows))):
        cx, cy = (k % cols + 0.5) * cell, (k // cols + 0.5) * cell
        d = draw(st.floats(1, cell / 4))
        jitter = draw(st.tuples(st.floats(-cell / 8, cell / 8), st.floats(-cell / 8, cell / 8)))
        at = (cx + jitter[0], cy + jitter[1])
        if draw(st.booleans()):
            targets.append(Body(f"id{k}", "particle", at, d))
        else:
            length = draw(st.floats(d, cell / 2))
            targets.append(Body(f"id{k}", "rod", at, d, draw(st.floats(-720, 720)), length))
    tol = Tolerance(draw(st.floats(0.1, 100)), draw(st.floats(0.1, 90)), draw(st.floats(0.01, 1)))
    return Layout((cols * cell, rows * cell), tuple(targets), (), tol, draw(st.none() | name))


@given(layouts())
def test_random_layouts_round_trip(layout):
    assert layout_from_dict(layout.to_dict()) == layout
    assert layout_from_dict(tomllib.loads(layout.dumps_toml())) == layout
    assert layout_from_dict(json.loads(layout.dumps_json())) == layout


@given(st.lists(st.tuples(coord, coord, st.floats(1, 500), st.floats(0, 1), st.booleans(),
                          st.sampled_from(["particle", "rod", "wire"]), finite), max_size=8))
def test_random_environments_round_trip(rows):
    objects = []
    for i, (x, y, d, c, edge, kind, angle) in enumerate(rows):
        if kind == "particle":
            objects.append(EnvObject(f"o{i}", kind, (x, y), d, None, None, c, edge))
        else:
            objects.append(EnvObject(f"o{i}", kind, (x, y), d, angle, d * 3, c, edge))
    env = Environment((1e4, 1e4), tuple(objects),
                      (EnvObstacle(((0.0, 0.0), (10.0, 0.0), (10.0, 10.5)), 3.5, True),), "x.gwy")
    assert environment_from_dict(json.loads(env.dumps())) == env


@given(st.lists(st.lists(st.tuples(finite, finite), min_size=2, max_size=6), max_size=5),
       st.none() | finite)
def test_random_plans_round_trip(paths, angle):
    ops = tuple(Operation(i + 1, f"o{i}", None if i % 2 else f"t{i}", tuple(p),
                          Expect(p[-1], angle)) for i, p in enumerate(paths))
    plan = Plan("lay", (Assignment("t0", "o0"),), ops, (Unfilled("t9", "no path"),))
    assert plan_from_dict(json.loads(plan.dumps())) == plan


@given(st.floats(0, 1e7), st.integers(0, 10**6), st.none() | st.integers(0, 2**63 - 1))
def test_random_reports_round_trip(t, n, seed):
    body = Body("o1", "rod", (1.0, 2.0), 10.0, 33.0, 100.0)
    rep = Report("s.toml", None, seed, (Body("t1", "particle", (5.0, 5.0), 3.0),), (body,), (body,),
                 (), ("o1",), (), Counts(n, n, 0, n), InstrumentTime(t, t, t, t, 4 * t),
                 WallTime(t, 0.0, t, 2 * t))
    assert report_from_dict(json.loads(rep.dumps())) == rep


# -- rejections in the JSON formats ---------------------------------------------------

def _golden(name: str) -> dict:
    return json.loads((GOLDEN / name).read_text())


@pytest.mark.parametrize("edit,fragment", [
    (lambda d: d["objects"][0].update(confidence=1.5), "objects[1].confidence: must be at most 1"),
    (lambda d: d["objects"][1].pop("angle"), "objects[2].angle: missing required key for a rod"),
    (lambda d: d["objects"][0].update(kind="blob"), "objects[1].kind: must be one of"),
    (lambda d: d["objects"][0].update(edge="yes"), "objects[1].edge: must be true or false"),
    (lambda d: d["obstacles"][0].update(height=-1), "obstacles[1].height: must not be negative"),
    (lambda d: d.update(area=[0, 1]), "area: width must be positive"),
])
def test_environment_rejections(edit, fragment):
    data = _golden("env.json")
    edit(data)
    with pytest.raises(InputError, match=None) as info:
        environment_from_dict(data, "env.json")
    assert fragment in str(info.value)


@pytest.mark.parametrize("edit,fragment", [
    (lambda d: d["operations"][0].update(tip_path=[[0, 0]]), "operations[1].tip_path: must have at least 2"),
    (lambda d: d["operations"][0].update(kind="pull"), "operations[1].kind: must be one of"),
    (lambda d: d["operations"][1].update(id=1), "operations[2].id: duplicate operation id 1"),
    (lambda d: d["operations"][0]["expect"].update(angle="x"), "operations[1].expect.angle: must be a number"),
    (lambda d: d["assignment"][0].pop("object"), "assignment[1].object: missing required key"),
])
def test_plan_rejections(edit, fragment):
    data = _golden("plan.json")
    edit(data)
    with pytest.raises(InputError) as info:
        plan_from_dict(data, "plan.json")
    assert fragment in str(info.value)


@pytest.mark.parametrize("edit,fragment", [
    (lambda d: d["counts"].update(pushes=-1), "counts.pushes: must not be negative"),
    (lambda d: d["counts"].update(pushes=1.5), "counts.pushes: must be an integer"),
    (lambda d: d["instrument_time"].pop("travel"), "instrument_time.travel: missing required key"),
    (lambda d: d.update(pushed=[""]), "pushed[1]: must be an object id"),
    (lambda d: d.pop("wall_time"), "wall_time: missing required key"),
])
def test_report_rejections(edit, fragment):
    data = _golden("report.json")
    edit(data)
    with pytest.raises(InputError) as info:
        report_from_dict(data, "report.json")
    assert fragment in str(info.value)


def test_value_types_refuse_bad_values_in_code():
    with pytest.raises(ValueError):
        Body("x", "particle", (0.0, math.nan), 1.0)
    with pytest.raises(ValueError):
        Body("x", "rod", (0.0, 0.0), 10.0, 0.0, 5.0)
    with pytest.raises(ValueError):
        Operation(1, "o", None, ((0.0, 0.0),), Expect((0.0, 0.0)))
    with pytest.raises(ValueError):
        Expect((0.0, math.inf))
    assert Keepout(((0.0, 0.0), (1.0, 0.0), (1.0, 1.0))).geometry().area == 0.5
