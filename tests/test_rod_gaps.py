"""A rod slot between two electrodes that span the area (the ``device`` family's): the
order of a rod and the particles flanking it, the sideways walk in, spare objects when
the assigned one has no way in, and electrodes planned where they are, not where the
full scan's drifting rows drew them (issue 14: the device family's rod was never pushed)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import shapely
from test_planner import filled, replay

from nanoasm.bodies import Body
from nanoasm.cad.layout import Keepout, Layout, Tolerance
from nanoasm.dryrun import dry_run
from nanoasm.executor.drift_steps import unskewed_obstacles
from nanoasm.executor.strategy import ExecOptions
from nanoasm.planner import check_plan, plan_assembly
from nanoasm.planner.freespace import FreeSpace
from nanoasm.planner.options import PlanOptions
from nanoasm.planner.rods import approach_pose, roomy
from nanoasm.planner.sequence import order
from nanoasm.world.environment import EnvObject, EnvObstacle, Environment
from nanoasm.world.families import family_case

A = 4000.0
C = A / 2
#: Two pads from the area's edges to a 1400 nm gap, 1600 nm tall: the area's upper and
#: lower halves meet only in the gap.
PADS = (((0.0, C - 800), (C - 700, C - 800), (C - 700, C + 800), (0.0, C + 800)),
        ((C + 700, C - 800), (A, C - 800), (A, C + 800), (C + 700, C + 800)))
BAR = Body("bar", "rod", (C, C), 90.0, 0.0, 1200.0)
#: Two particle slots below the rod slot, 60 nm clear of it.
BELOW = (Body("p1", "particle", (C - 300, C - 150), 90.0), Body("p2", "particle", (C + 300, C - 150), 90.0))


def _case(objects) -> tuple[Layout, Environment]:
    layout = Layout((A, A), (BAR, *BELOW), tuple(Keepout(p) for p in PADS), Tolerance(), "gap")
    return layout, Environment((A, A), tuple(objects), tuple(EnvObstacle(p, 30.0) for p in PADS))


def _plan_fills_every_slot(layout, env):
    plan, _ = plan_assembly(layout, env)
    assert not plan.unfilled, plan.unfilled
    final = replay(plan, env)
    assert filled(plan, layout, final) == {"bar", "p1", "p2"}
    assert check_plan(plan, layout, env) == []
    return plan


def test_a_rod_from_below_goes_before_the_particles_that_would_bar_its_way():
    """The rod comes up through the gap: particles put first below its slot would shut
    the gap (they used to be: the rod was then never pushed). The particles nearest their
    slots lie above the gap and cannot pass the rod in its slot: spares from below fill
    the slots."""
    objects = (EnvObject("r", "rod", (C - 400, 800.0), 90.0, 70.0, 1200.0),
               EnvObject("a", "particle", (C + 150, C + 1000), 90.0),      # above the gap
               EnvObject("e", "particle", (C - 250, C + 1000), 90.0),
               EnvObject("b", "particle", (1300.0, 600.0), 90.0),
               EnvObject("d", "particle", (2900.0, 500.0), 90.0))
    layout, env = _case(objects)
    plan = _plan_fills_every_slot(layout, env)
    first = [op.object for op in plan.operations]
    assert first[0] == "r" and set(first[first.index("r"):len(first) - first[::-1].index("r")]) == {"r"}
    assert {a.object for a in plan.assignment} == {"r", "b", "d"}


def test_a_rod_from_above_lets_a_particle_below_go_first():
    """Particle slots on the far side of the rod slot from where the rod comes do not bar
    its way, and a particle from above must pass the slot before the rod shuts the gap."""
    objects = (EnvObject("r", "rod", (C - 300, C + 1250), 90.0, 10.0, 1200.0),
               EnvObject("a", "particle", (C + 150, C + 900), 90.0),
               EnvObject("b", "particle", (1500.0, 700.0), 90.0),
               EnvObject("d", "particle", (2600.0, 600.0), 90.0))
    layout, env = _case(objects)
    plan = _plan_fills_every_slot(layout, env)
    assigned = {a.target: a.object for a in plan.assignment}
    assert assigned["p2"] == "a"
    ops = [op.object for op in plan.operations]
    assert ops.index("a") < ops.index("r")


def test_order_of_crossing_rod_and_particle_moves_does_not_depend_on_their_listing():
    targets = {t.id: t for t in (BAR, *BELOW)}
    objects = {"r": Body("r", "rod", (C - 400, 800.0), 90.0, 70.0, 1200.0),
               "a": Body("a", "particle", (C + 150, C + 1000), 90.0),
               "b": Body("b", "particle", (1300.0, 600.0), 90.0)}
    moves = [("p1", "b"), ("p2", "a"), ("bar", "r")]
    efforts = {t: math.dist(objects[o].at, targets[t].at) for t, o in moves}
    for listing in (moves, moves[::-1]):
        nodes, _ = order(listing, targets, objects, set(), 20.0, efforts)
        fills = [n[1] for n in nodes if n[0] == "fill"]
        assert fills.index("bar") < fills.index("p2")


def test_the_approach_pose_lies_outside_the_gap_on_the_rods_side():
    options = PlanOptions()
    space = FreeSpace((A, A), [(shapely.Polygon(p), 0.0) for p in PADS], {}, options.clearance)
    assert not roomy(space, BAR, options, None)           # no room to line up between the pads
    for start, sign in (((C, 300.0), -1), ((C, 3700.0), 1)):
        rod = Body("r", "rod", start, 90.0, 30.0, 1200.0)
        pre = approach_pose(space, BAR, options, None, rod)
        assert pre is not None and pre.angle == BAR.angle and pre.at[0] == pytest.approx(C)
        # beyond the pads (their half-height and the rod's radius), no further than needed
        beyond = sign * (pre.at[1] - C) - 800 - BAR.radius
        assert 0 < beyond <= 0.1 * BAR.length + options.clearance
        assert roomy(space, pre, options, None)


class _Drifting:
    """A drift estimate of a steady velocity: a full-scan point seen ``tau`` s after the
    epoch had drifted by ``v tau``."""

    epoch = 100.0
    v = np.array([-0.3, 0.25])

    def unskew(self, at, tau):
        return np.asarray(at, float) - self.v * tau


def test_obstacles_are_unskewed_vertex_by_vertex_with_their_rows_time():
    rows = (100.0, 2.0, 10.0)          # the first row's time, s a row, nm a row

    def row_time(y):
        return rows[0] + (y / rows[2] + 0.5) * rows[1]

    pad = EnvObstacle(((0.0, 0.0), (500.0, 0.0), (500.0, 1000.0), (0.0, 1000.0)), 30.0)
    (moved,) = unskewed_obstacles((pad,), _Drifting(), row_time)
    assert moved.height == pad.height
    for p, q in zip(pad.polygon, moved.polygon):
        tau = row_time(p[1]) - _Drifting.epoch
        assert q == pytest.approx(tuple(np.asarray(p) - _Drifting.v * tau))
    # the top corner, scanned 200 s after the bottom one, moves 60 nm further: the shear
    # a drifting scan draws is taken out
    assert moved.polygon[2][0] - moved.polygon[1][0] == pytest.approx(0.3 * 200.0)


class _Torn(_Drifting):
    """A jump of 600 nm in x taken to count from 50 s after the epoch (rows from y = 245 nm
    on): the rows after it move back by it."""

    def unskew(self, at, tau):
        return super().unskew(at, tau) - (np.array([600.0, 0.0]) if tau >= 50.0 else 0.0)


def test_an_obstacle_whose_rows_a_torn_scan_moved_across_each_other_stays_a_valid_keep_out():
    """Where the jump is placed between two references' rows, the rows between move by it or
    not as they may not have been: a pad's ring then crossed itself, and the planner's union
    of keep-outs failed (mixed seed 1, 300 nm at 250 s). It becomes the hull of its vertices."""
    rows = (100.0, 2.0, 10.0)

    def row_time(y):
        return rows[0] + (y / rows[2] + 0.5) * rows[1]

    pad = EnvObstacle(((0.0, 0.0), (500.0, 0.0), (500.0, 300.0), (500.0, 1000.0), (0.0, 1000.0), (0.0, 200.0)), 30.0)
    raw = [tuple(_Torn().unskew(np.asarray(p, float), row_time(p[1]) - _Torn.epoch)) for p in pad.polygon]
    assert not shapely.Polygon(raw).is_valid
    (moved,) = unskewed_obstacles((pad,), _Torn(), row_time)
    ring = shapely.Polygon(moved.polygon)
    assert ring.is_valid and all(ring.buffer(1e-6).contains(shapely.Point(p)) for p in raw)
    (steady,) = unskewed_obstacles((pad,), _Drifting(), row_time)   # a valid ring is kept as it is
    assert len(steady.polygon) == len(pad.polygon)


def test_a_rod_whose_way_the_gaps_particle_slots_would_bar_is_planned_first():
    """mixed seed 5: the order from straight corridors put the four particle slots in the
    gap between the electrodes before the rod slot beyond it; filled, they barred the
    rod's way (its zigzag stuck among them, 'no path', 4 of 5 slots on every run). A rod
    slot left with no path after particle slots were filled is planned again with the
    rods first: every slot filled, the rod's too, and the verdict the truth."""
    scene, layout = family_case("mixed", 5)
    out = dry_run(scene, layout, options=ExecOptions(strategy="full"))
    assert not out.summary.plan.unfilled, out.summary.plan.unfilled
    slots = {t.id for t in layout.targets}
    assert set(out.truly_filled) == slots and set(out.filled) == slots and not out.disagreements


def _against_right_pad(angle: float, into: float, length: float = 1250.0) -> EnvObject:
    """A rod in the gap whose upper end lies ``into`` nm into the right pad's outline."""
    half = (length - 90.0) / 2
    x = C + 700 - 45 + into - abs(math.cos(math.radians(angle))) * half
    return EnvObject("r", "rod", (x, C + 300), 90.0, angle, length)


@pytest.mark.parametrize("angle", [45.0, 135.0])
def test_a_rod_against_a_pad_is_pushed_off_it_first(angle):
    """A push that goes astray in the gap can leave a rod against a pad (device seeds 2, 6
    and 9: 350-506 nm off course). It used to be held there for good, and its slot and
    the particle slots it barred stayed empty. Now its first pushes only take it away
    from the pad, and it ends a tip's radius clear of it; the rest of the plan touches
    nothing."""
    rod = _against_right_pad(angle, 15.0)
    pad = shapely.Polygon(PADS[1])
    assert shapely.distance(rod.geometry(), pad) < rod.radius          # it lies on the pad
    plan = _plan_fills_every_slot(*_case([rod, EnvObject("a", "particle", (C - 250, C - 1200), 90.0),
                                          EnvObject("b", "particle", (C + 250, C - 1200), 90.0)]))
    gaps = [shapely.distance(rod.geometry(), pad)]
    for op in (o for o in plan.operations if o.object == "r"):
        pose = Body("r", "rod", op.expect.at, 90.0, op.expect.angle, rod.length)
        gaps.append(shapely.distance(pose.geometry(), pad))
        if gaps[-1] >= rod.radius + 10.0:
            break
    assert gaps[-1] >= rod.radius + 10.0 and all(b >= a - 0.05 for a, b in zip(gaps, gaps[1:])), gaps


def test_a_rod_whose_axis_lies_on_a_pad_is_held():
    """A rod whose axis crosses into a pad lies on it: it is not pushed, and its slot
    says why."""
    plan, _ = plan_assembly(*_case([_against_right_pad(45.0, 60.0)]))
    (bar,) = [u for u in plan.unfilled if u.target == "bar"]
    assert "'r' may not" in bar.reason and "keep-out" in bar.reason


def test_a_device_rod_left_against_a_pad_is_pushed_off_it_and_arrives():
    """device seed 9: a push at the gap's entrance went 381 nm astray and left the rod 4 nm
    inside the right pad's outline, beside a particle on the pad. The rod was held there
    (and, once it was not, the simulated pad blocked every move of it, even away), so the
    rod slot and a particle slot it barred stayed empty (7 of 9). Now it is pushed off and
    arrives, the verdict the truth. Every other slot was filled too until 3c8cd49: since a
    shoved neighbour is located again, the run knows where the rod carried a spare particle
    (353 nm) and no replan assigns it to s7, for which no other particle has a path; the
    report says s7 is unfilled (bench/RESULTS_rods.md, 2026-12-07)."""
    scene, layout = family_case("device", 9)
    out = dry_run(scene, layout, options=ExecOptions(strategy="full"))
    slots = {t.id for t in layout.targets}
    assert "bar" in out.truly_filled and not out.disagreements
    assert set(out.truly_filled) >= slots - {"s7"}


def test_a_rod_slot_with_no_way_in_says_why_and_where():
    """Issue 14: a search that finds no path says which constraint, where. The gap is
    closed from below by a keep-out: the rod below cannot reach the slot, and the reason
    names the keep-out in its straight way, where the search came nearest and that no
    SE(2) path was found."""
    lid = ((C - 700, C - 800), (C + 700, C - 800), (C + 700, C - 700), (C - 700, C - 700))
    layout = Layout((A, A), (BAR,), tuple(Keepout(p) for p in (*PADS, lid)), Tolerance(), "gap")
    env = Environment((A, A), (EnvObject("r1", "rod", (C, 900.0), 90.0, 0.0, 1200.0),),
                      tuple(EnvObstacle(p, 30.0) for p in PADS))
    plan, _ = plan_assembly(layout, env, PlanOptions(budget=0.3))
    (u,) = plan.unfilled
    assert u.target == "bar" and u.reason.startswith("no path for 'r1': ")
    assert "the straight way is blocked by keep-out 3" in u.reason
    near = re.search(r"nearest at \((\d+), (\d+)\) at (\d+)°, (\d+) nm and (\d+)° from the slot", u.reason)
    assert near, u.reason
    x, y, _, dist, _ = (int(v) for v in near.groups())
    assert y < C - 700 and dist == pytest.approx(math.dist((x, y), (C, C)), abs=1)   # below the lid
    assert "no SE(2) path (OMPL)" in u.reason


def test_a_particle_in_a_rods_way_whose_slot_is_on_the_rods_side_waits_for_the_rod():
    """The bundled bowtie's order (seeds 1 and 8 left its rod slot 'no path'): a particle
    lying in the rod's corridor used to go first, to a slot beside the rod's way on the
    side the rod comes from; there it barred the way for good. The rod goes first."""
    targets = {"bar": Body("bar", "rod", (2500.0, 1500.0), 80.0, 0.0, 800.0),
               "l1": Body("l1", "particle", (2380.0, 2500.0), 100.0)}
    objects = {"r": Body("r", "rod", (3662.0, 4121.0), 80.0, 117.5, 800.0),
               "a": Body("a", "particle", (2600.0, 2000.0), 100.0)}   # in the rod's corridor
    moves = [("l1", "a"), ("bar", "r")]
    efforts = {t: math.dist(objects[o].at, targets[t].at) for t, o in moves}
    for listing in (moves, moves[::-1]):
        fills = [n[1] for n in order(listing, targets, objects, set(), 20.0, efforts)[0] if n[0] == "fill"]
        assert fills == ["bar", "l1"]
    # a particle slot on the far side of the rod's slot: the particle clears the way first
    far = {**targets, "l1": Body("l1", "particle", (2380.0, 800.0), 100.0)}
    fills = [n[1] for n in order(moves, far, objects, set(), 20.0, efforts)[0] if n[0] == "fill"]
    assert fills == ["l1", "bar"]
