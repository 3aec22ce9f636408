"""Planner: assignment, sequencing, collision-free pushes, rod zigzags, replanning."""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, example as case, given, settings, strategies as st

from nanoasm.bodies import Body
from nanoasm.cad.layout import Keepout, Layout, Tolerance, load_layout, size_ok
from nanoasm.examples import path as example
from nanoasm.planner import PlanOptions, Replanner, check_plan, plan_assembly
from nanoasm.planner.assign import axis_error, in_slot
from nanoasm.planner.rods import simulate_push
from nanoasm.world.environment import EnvObject, EnvObstacle, Environment
from nanoasm.world.random_scene import SceneSpec, random_scene


def env_of(bodies, area=(5000.0, 5000.0), obstacles=()) -> Environment:
    return Environment(area, tuple(EnvObject(b.id, b.kind, b.at, b.diameter, b.angle, b.length)
                                   for b in bodies), tuple(obstacles))


def particle(i, x, y, d=100.0):
    return Body(f"o{i}", "particle", (float(x), float(y)), d)


def layout_of(targets, area=(5000.0, 5000.0), keepouts=()) -> Layout:
    return Layout(area, tuple(targets), tuple(Keepout(k) for k in keepouts), Tolerance(), "t")


def replay(plan, env, tip_radius=10.0):
    """Final poses after replaying a plan: particles to their expects, rods by the pivot
    model from their tip paths (independently of the planner's own bookkeeping)."""
    objects = {o.id: Body(o.id, o.kind, o.at, o.diameter, o.angle, o.length) for o in env.objects}
    for op in plan.operations:
        o = objects[op.object]
        if o.kind == "rod":
            objects[o.id] = simulate_push(o, op.tip_path[0], op.tip_path[-1], tip_radius)
        else:
            objects[o.id] = Body(o.id, o.kind, op.expect.at, o.diameter)
    return objects


def filled(plan, layout, final):
    tol = layout.tolerance
    return {a.target for a in plan.assignment if in_slot(layout.target(a.target), final[a.object], tol)}


def test_straight_pushes_fill_a_sparse_bowtie():
    layout = load_layout(example("bowtie.toml"))
    scene = random_scene(SceneSpec(area=(5000.0, 5000.0), particles=30, rods=3, particle_diameter=(90, 110),
                                   rod_length=(700, 900), rod_diameter=(70, 90)), 1)
    env = env_of(scene.objects)
    plan, stats = plan_assembly(layout, env)
    assert not plan.unfilled
    assert check_plan(plan, layout, env) == []
    final = replay(plan, env)
    assert filled(plan, layout, final) == {t.id for t in layout.targets}
    assert stats.path_ratio == pytest.approx(1.0) and set(stats.particle_turns) == {0}
    # each particle push starts behind the object on the line of the push
    for op in plan.operations:
        if env.object(op.object).kind == "particle":
            (x0, y0), (x1, y1) = op.tip_path
            ex, ey = op.expect.at
            assert math.isclose(math.dist((x1, y1), (ex, ey)), 100 / 2 + 10, rel_tol=0.25)


def test_detour_around_a_wall_uses_few_straight_segments():
    wall = [(2400.0, 500.0), (2600.0, 500.0), (2600.0, 4500.0), (2400.0, 4500.0)]
    layout = layout_of([Body("p", "particle", (4000.0, 2500.0), 100.0)], keepouts=[wall])
    env = env_of([particle(1, 1000, 2500)])
    plan, stats = plan_assembly(layout, env)
    assert not plan.unfilled
    assert check_plan(plan, layout, env) == []
    assert 2 <= len(plan.operations) <= 4          # around one end of the wall
    assert stats.path_ratio > 1.0
    assert replay(plan, env)["o1"].at == (4000.0, 2500.0)


def test_a_slot_held_by_another_object_is_cleared_first():
    layout = layout_of([Body("p", "particle", (2500.0, 2500.0), 100.0)])
    env = env_of([particle(1, 2500, 2500, 40.0), particle(2, 1000, 1000)])    # o1 too small
    plan, _ = plan_assembly(layout, env)
    assert [a.object for a in plan.assignment] == ["o2"]
    first = plan.operations[0]
    assert first.object == "o1" and first.target is None                      # parked
    assert check_plan(plan, layout, env) == []
    final = replay(plan, env)
    assert in_slot(layout.target("p"), final["o2"], layout.tolerance)


def test_objects_already_in_their_slot_stay_and_reasons_are_given():
    layout = layout_of([Body("a", "particle", (1000.0, 1000.0), 100.0),
                        Body("b", "particle", (3000.0, 1000.0), 60.0),
                        Body("c", "rod", (2500.0, 3000.0), 80.0, 0.0, 800.0)])
    env = env_of([particle(1, 1005, 998)])
    plan, _ = plan_assembly(layout, env)
    assert [(a.target, a.object) for a in plan.assignment] == [("a", "o1")]
    assert plan.operations == ()
    reasons = {u.target: u.reason for u in plan.unfilled}
    assert reasons["b"] == "no particle of diameter 60 +/- 25%"
    assert reasons["c"] == "no rod of length 800 and diameter 80 +/- 25%"


def test_wires_edge_objects_and_slender_rods_are_never_assigned():
    layout = layout_of([Body("r", "rod", (2500.0, 2500.0), 50.0, 0.0, 1000.0)])
    objects = (EnvObject("w", "wire", (1000.0, 1000.0), 50.0, 0.0, 1000.0),
               EnvObject("e", "rod", (1000.0, 4000.0), 50.0, 0.0, 1000.0, edge=True),
               EnvObject("s", "rod", (3500.0, 1000.0), 50.0, 0.0, 1000.0, confidence=0.2))
    plan, _ = plan_assembly(layout, Environment((5000.0, 5000.0), objects))
    assert plan.assignment == () and plan.unfilled[0].target == "r"


def test_identical_objects_assignment_is_deterministic():
    targets = [Body(f"t{i}", "particle", (1000.0 + 400 * i, 2500.0), 100.0) for i in range(5)]
    objs = [particle(i, 1000 + 400 * i, 1000) for i in range(5)] + [particle(9, 3000, 4000)]
    layout, env = layout_of(targets), env_of(objs)
    a = plan_assembly(layout, env, PlanOptions(seed=3))[0]
    b = plan_assembly(layout, env, PlanOptions(seed=3))[0]
    assert a == b
    assert sorted(x.object for x in a.assignment) == [f"o{i}" for i in range(5)]


def test_rod_zigzag_reaches_its_slot_under_the_pivot_model():
    layout = layout_of([Body("bar", "rod", (2500.0, 1500.0), 80.0, 0.0, 800.0)])
    rod = Body("r", "rod", (1000.0, 3000.0), 80.0, 33.0, 800.0)
    env = env_of([rod])
    plan, stats = plan_assembly(layout, env)
    assert not plan.unfilled
    final = replay(plan, env)["r"]
    tol = layout.tolerance
    assert math.dist(final.at, (2500.0, 1500.0)) <= tol.position
    assert axis_error(final.angle, 0.0) <= tol.angle
    assert stats.rod_pushes[0] == len(plan.operations) < 80
    # every push is near an end, never near the middle (l = L/2, the bifurcation), and
    # says which way the rod will point
    pose = rod
    for op in plan.operations:
        assert op.expect.angle is not None and 0 <= op.expect.angle < 180
        c, s = math.cos(math.radians(pose.angle)), math.sin(math.radians(pose.angle))
        along = (op.tip_path[0][0] - pose.at[0]) * c + (op.tip_path[0][1] - pose.at[1]) * s
        assert abs(along) > 0.25 * pose.length         # 0.3 L at the default push point 0.2 L from an end
        pose = simulate_push(pose, op.tip_path[0], op.tip_path[-1], 10.0)
    assert check_plan(plan, layout, env) == []


@settings(max_examples=int(__import__("os").environ.get("PLANNER_EXAMPLES", 12)), deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), particles=st.integers(1, 25), rods=st.integers(0, 2),
       obstacles=st.integers(0, 2))
@case(seed=310, particles=8, rods=2, obstacles=1)   # a particle 5 nm larger than its slot touched a neighbour there
def test_random_scenes(seed, particles, rods, obstacles):
    scene = random_scene(SceneSpec(area=(6000.0, 6000.0), particles=particles, rods=rods,
                                   obstacles=obstacles, obstacle_size=(300.0, 900.0),
                                   particle_diameter=(60.0, 120.0), rod_length=(500.0, 900.0)), seed)
    env = Environment(scene.area, tuple(EnvObject(o.id, o.kind, o.at, o.diameter, o.angle, o.length)
                                        for o in scene.objects),
                      tuple(EnvObstacle(ob.polygon, ob.height) for ob in scene.obstacles))
    targets = [Body("a", "particle", (1500.0, 3000.0), 90.0), Body("b", "particle", (1700.0, 3000.0), 90.0),
               Body("c", "particle", (4200.0, 4800.0), 70.0)]
    if rods:
        targets.append(Body("r", "rod", (3000.0, 1200.0), 80.0, 20.0, 700.0))
    layout = layout_of(targets, area=(6000.0, 6000.0))
    plan, _ = plan_assembly(layout, env, PlanOptions(budget=0.3))
    # every slot is either assigned or explained, never both
    assigned = [a.target for a in plan.assignment]
    explained = [u.target for u in plan.unfilled]
    assert sorted(assigned + explained) == sorted(t.id for t in targets)
    assert all(u.reason for u in plan.unfilled)
    # assignments are compatible
    for a in plan.assignment:
        t, o = layout.target(a.target), env.object(a.object)
        assert o.kind == t.kind and size_ok(t, o, layout.tolerance)
    # no NaN, no collision with keep-outs, obstacles or other objects
    for op in plan.operations:
        assert all(math.isfinite(v) for p in op.tip_path for v in p)
        assert all(math.isfinite(v) for v in op.expect.at)
    assert check_plan(plan, layout, env) == []


def test_replanning_is_cheap_when_nothing_moved_and_replans_when_something_did():
    layout = load_layout(example("bowtie.toml"))
    scene = random_scene(SceneSpec(area=(5000.0, 5000.0), particles=20, particle_diameter=(90, 110)), 2)
    env = env_of(scene.objects)
    rp = Replanner(layout)
    plan = rp.start(env)
    n = len(plan.operations)
    assert n > 2
    # the belief after two pushes is where the plan expected it: the remainder stands
    from nanoasm.planner.replan import expected

    belief = Environment(env.area, tuple(expected(env, plan, 2).values()))
    rest = rp.remainder(belief, 2)
    assert not rest.replanned and rest.plan.operations == plan.operations[2:]
    # an object was found 60 nm from where it should be: replan from the belief
    moved = [o if o.id != plan.operations[2].object else
             EnvObject(o.id, o.kind, (o.at[0] + 60.0, o.at[1]), o.diameter) for o in belief.objects]
    rest = rp.remainder(Environment(env.area, tuple(moved)), 2)
    assert rest.replanned and rest.deviation == pytest.approx(60.0)
    assert rp.replans == 1
    assert check_plan(rest.plan, layout, Environment(env.area, tuple(moved))) == []


def test_planner_names_are_checked():
    with pytest.raises(ValueError, match="planner: must be one of"):
        PlanOptions(planner="astar")


def test_every_planner_finds_a_detour_and_returns(tmp_path):
    """Each OMPL planner, in a subprocess with a deadline: none may hang (a planner that
    calls back into Python from its own thread would)."""
    import subprocess
    import sys

    from nanoasm.planner import PLANNERS

    code = (
        "from nanoasm.bodies import Body\n"
        "from nanoasm.cad.layout import Keepout, Layout, Tolerance\n"
        "from nanoasm.planner import PlanOptions, plan_assembly\n"
        "from nanoasm.world.environment import EnvObject, Environment\n"
        "import sys\n"
        "wall = ((2400.0, 500.0), (2600.0, 500.0), (2600.0, 4500.0), (2400.0, 4500.0))\n"
        "lay = Layout((5000.0, 5000.0), (Body('p', 'particle', (4000.0, 2500.0), 100.0),),"
        " (Keepout(wall),), Tolerance())\n"
        "env = Environment((5000.0, 5000.0), (EnvObject('o1', 'particle', (1000.0, 2500.0), 100.0),))\n"
        "for name in sys.argv[1:]:\n"
        "    plan, _ = plan_assembly(lay, env, PlanOptions(planner=name, budget=1.0))\n"
        "    assert not plan.unfilled, name\n"
        "print('ok')\n"
    )
    # run outside the checkout, whose nanoasm/ folder would shadow the installed package
    run = subprocess.run([sys.executable, "-c", code, *PLANNERS], capture_output=True, text=True,
                         timeout=120, cwd=tmp_path)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr
