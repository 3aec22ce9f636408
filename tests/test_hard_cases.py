"""Hard cases through the simulated AFM, the drift filter, the DAC stream and whole
dry-runs: each shows no NaN, a bounded error, and the same output for the same input.

The closed forms at the same points are tested where the models live
(``test_physics_pivot``, ``test_physics_particle``, ``test_physics_cantilever``,
``test_kalman``, ``test_dac``, ``test_planner``); these take them end to end.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest
import shapely

from nanoasm import dryrun
from nanoasm.bodies import Body
from nanoasm.cad.layout import Keepout, Layout
from nanoasm.drift import DriftFilter, DriftFilterParams
from nanoasm.executor.monitor import PushMonitor
from nanoasm.executor.strategy import ExecOptions
from nanoasm.instrument import InstrumentConfig
from nanoasm.world.cantilever import tip_force_afm
from nanoasm.world.families import family_case
from nanoasm.world.params import DriftParams, FaultParams, FrictionParams, TipParams
from nanoasm.world.particle_push import theta_max_deg
from nanoasm.world.scene import Scene
from nanoasm.world.sim import SimulatedAFM
from simkit import EXACT, particle, push, rod, world


def numbers(doc) -> list[float]:
    """Every number in a nested document."""
    if isinstance(doc, dict):
        return [x for v in doc.values() for x in numbers(v)]
    if isinstance(doc, (list, tuple)):
        return [x for v in doc for x in numbers(v)]
    return [float(doc)] if isinstance(doc, (int, float)) and not isinstance(doc, bool) else []


def no_nan(*arrays) -> bool:
    return all(np.all(np.isfinite(np.asarray(a, float))) for a in arrays)


def outcome(scene, layout, seed=1, strategy="full", **knobs):
    """A dry-run's report without its wall time (which differs between runs), and the outcome."""
    out = dryrun.dry_run(scene, layout, seed=seed, options=ExecOptions(strategy=strategy, **knobs))
    doc = {k: v for k, v in out.report.to_dict().items() if k != "wall_time"}
    assert no_nan(numbers(doc)), "NaN or infinity in the report"
    return doc, out


def twice(scene, layout, seed=1, strategy="full", **knobs):
    """Run the dry-run twice; the same input must give the same report."""
    a, out = outcome(scene, layout, seed, strategy, **knobs)
    b, _ = outcome(scene, layout, seed, strategy, **knobs)
    assert a == b, "the same dry-run twice gave two reports"
    return out


def particles_only(objects, area=1500.0, drift=(0.1, -0.05)) -> Scene:
    return Scene((area, area), tuple(objects), params=dataclasses.replace(
        EXACT, drift=DriftParams(drift, 0.1)), seed=1)


# -- l -> L/2: a rod pushed ever closer to its middle (the pivot bifurcation) ------------

def _rod_push(u: float, preload: float = 300.0):
    """Push a 400 x 50 nm rod 160 nm along +y at ``u`` nm from its middle; its final pose
    and the simulator's count of slips."""
    params = dataclasses.replace(EXACT, scanner=InstrumentConfig(preload=preload))
    sim = world([rod((2000, 2000), 0.0, 400.0)], seed=3, params=params)
    push(sim, (2000 + u, 1900), (2000 + u, 2060))
    (r,) = sim.truth()
    return r, sim.diagnostics()["slips"]


def _turn(r) -> float:
    return (r.angle + 90.0) % 180.0 - 90.0


@pytest.mark.parametrize("u", [-60.0, -20.0, -8.0, -1.0, -1e-3, -1e-9, 0.0, 1e-9, 1e-3, 1.0, 8.0, 20.0, 60.0])
def test_l_to_half_L(u):
    """A push at l = L/2 + u (the pivot bifurcation at u = 0), with a preload that can
    push a rod at its middle (fL, eq. 4.12): bounded turns, mirror images either side."""
    (r, slips), again = _rod_push(u), _rod_push(u)
    assert no_nan(r.at, r.angle) and (r, slips) == again and slips == 0
    assert abs(_turn(r)) < 30.0 and 50.0 < math.dist(r.at, (2000, 2000)) < 160.0
    if abs(u) >= 20.0:                   # outside the bifurcation band (2 % of L) the side decides
        mirror, _ = _rod_push(-u)
        assert 20.0 < abs(_turn(r)) and np.sign(_turn(r)) == -np.sign(_turn(mirror))
        assert abs(_turn(r)) == pytest.approx(abs(_turn(mirror)), abs=1.0)
    if abs(u) <= 1.0:                    # at the middle it mostly slides
        assert abs(_turn(r)) < 5.0


def test_l_at_half_L_with_too_little_force_slips_over():
    """With the default preload the tip cannot push a rod at its middle (it needs fL, not
    the (√2 − 1)fL of an end): it slips over and the rod stays, not a wild turn."""
    r, slips = _rod_push(0.0, preload=100.0)
    assert slips == 1 and (r.at, r.angle) == ((2000.0, 2000.0), 0.0)
    end, slips = _rod_push(-150.0, preload=100.0)
    assert slips == 0 and abs(_turn(end)) > 10.0


# -- theta -> theta_max: the tip's push angle up to where it can no longer push ---------

def _particle_push(half_angle: float):
    """A 350 nm push of a particle with a tip of this half angle γ (θ = θx + γ), pressed
    with 96 nN (800 nm preload, 9 V of S_n: the most the photodiode's 10 V allows)."""
    params = dataclasses.replace(EXACT, tip=TipParams(half_angle=half_angle), friction=FrictionParams(scatter=0.0),
                                 scanner=InstrumentConfig(preload=800.0))
    sim = world([particle((2000, 2000))], params=params)
    block, _ = push(sim, (2000, 1850), (2000, 2200))
    return sim.truth()[0], block


def test_theta_to_theta_max():
    """The normal force a push needs diverges as θ → θmax = atan(1/μos) (eq. 4.7); with a
    finite force the tip slips over from some θ below θmax (72-74° here) and never pushes
    at or beyond it: the particle goes all the way or stays, with nothing in between."""
    th_max = theta_max_deg(FrictionParams().mu_os)          # 78.69 deg at mu_os = 0.2
    gammas = (20.0, 60.0, 70.0, 72.0, 74.0, th_max - 1.0, th_max - 0.1, th_max - 1e-6, th_max, 80.0)
    moved = []
    for gamma in gammas:
        p, block = _particle_push(gamma)
        assert no_nan(p.at, block.s_n, block.s_l)
        q, again = _particle_push(gamma)
        assert (p, block.s_n.tolist()) == (q, again.s_n.tolist())
        moved.append(math.dist(p.at, (2000, 2000)))
    full = 350.0 - 115.0                                    # the push beyond first contact
    assert all(abs(d - full) < 2.0 for d in moved[:4]) and all(d == 0.0 for d in moved[4:])


# -- phi -> 0: a push along the cantilever, where F_x is unmeasurable -------------------

def _stuck_push(angle_deg: float):
    """Push a stuck particle 300 nm past its centre at ``angle_deg`` from the lever's axis."""
    params = dataclasses.replace(EXACT, faults=FaultParams(stuck_object=1.0))
    sim = world([particle((2000, 2000))], params=params)
    d = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    block, codes = push(sim, np.array([2000.0, 2000.0]) - 150 * d, np.array([2000.0, 2000.0]) + 300 * d)
    contact = sim.config.codes_to_nm(codes)[:, 2] < 0
    return block.s_n[contact], block.s_l[contact], d, sim


@pytest.mark.parametrize("angle", [0.0, 1e-7, 1.0, 90.0])
def test_tip_moving_along_the_cantilever(angle):
    """Pushed along the lever (phi = 0) a stuck particle shows no lateral signal: F_y = 0
    and F_x is unmeasurable (eq. 3.11). The force estimate stays bounded and finite; across
    the lever (phi = 90) the same stuck push shows."""
    s_n, s_l, d, sim = _stuck_push(angle)
    again = _stuck_push(angle)
    assert (s_n.tolist(), s_l.tolist()) == (again[0].tolist(), again[1].tolist())
    force = tip_force_afm(s_n, s_l, np.broadcast_to(d, (len(s_n), 2)), sim.config.scan_angle)
    assert no_nan(s_n, s_l, force)
    lever = PushMonitor(sim.config.preload).lever
    f_y = lever.lateral_gain * np.abs(s_l - np.median(s_l))
    assert np.all(np.abs(force) < 1e4) and np.all(np.abs(force[:, 0]) <= 12 * lever.lateral_gain * 10)
    assert sim.truth() == sim.scene.objects                     # stuck: it stayed
    rise = f_y.max()
    if angle <= 1.0:
        assert rise < 10.0                                      # nN: the stuck push is invisible in S_l
    else:
        assert rise > 40.0                                      # across the lever it shows


def _stuck_case():
    objs = [particle((400, 750), 90, "a"), particle((1200, 300), 90, "b"), particle((300, 1250), 90, "c")]
    scene = dataclasses.replace(particles_only(objs), params=dataclasses.replace(
        particles_only(objs).params, faults=FaultParams(stuck_object=1.0)))
    return scene, Layout((1500.0, 1500.0), (Body("s1", "particle", (900.0, 750.0), 90.0),))   # a push along +x


@pytest.mark.parametrize("strategy", ["local-scan", "kalman"])
def test_a_stuck_push_along_the_cantilever_is_seen_by_the_scans(strategy):
    """Signals cannot tell (above); the scan after the push does, and the run gives up."""
    out = twice(*_stuck_case(), strategy=strategy)
    assert out.filled == () and out.errors["s1"] == pytest.approx(500.0, abs=10.0)   # never moved
    assert 1 <= out.report.counts.failed_pushes <= 5 and {c for _, c in out.summary.failures} == {"slipped"}


class Runaway(Exception):
    pass


def test_a_stuck_push_along_the_cantilever_is_not_retried_forever():
    """With replanning a push that keeps failing was once planned again and again (3048
    failed pushes and 3049 replans of this particle); the watch stops such a run early."""
    seen = {"plan": 0, "replanned": 0, "gave up": 0}
    dropped = []

    def watch(topic: str, doc: dict) -> None:
        if topic == "checkpoint" and doc["counts"]["pushes"] > 20:
            raise Runaway(f"{doc['counts']['pushes']} pushes of one stuck particle")
        if topic == "plan":
            seen["plan"] += 1
        if topic == "event":
            for key in ("replanned", "gave up"):
                seen[key] += doc.text.startswith(key)
            dropped.extend(doc.text.split("; ")[1:] if doc.text.startswith("replanned") else [])

    out = dryrun.dry_run(*_stuck_case(), seed=1, options=ExecOptions(strategy="full"), subscribers=[watch])
    assert 1 <= out.report.counts.failed_pushes <= 10
    # every replan is logged as a plan of its own; stuck objects were given up on
    assert seen["replanned"] >= 1 and seen["plan"] == 1 + seen["replanned"]
    assert seen["gave up"] >= 1
    # the replan that leaves the slot without an object says so, once, with the planner's reason
    assert dropped == [f"slot s1 left unfilled: {out.report.unfilled[0].reason}"]
    # ... and does not claim there is no particle of its size when all three were given up
    assert out.report.unfilled[0].reason == ("no particle of diameter 90 +/- 25% that may be pushed ('o1', 'o2', "
                                             "'o3' may not: given up, at the scan's edge, unsure or on a keep-out)")


# -- objects touching --------------------------------------------------------------------

AGGREGATE = [particle((400, 700), 90, "a"), particle((490, 700), 90, "b")]       # in contact
LONERS = [particle((1100, 400), 90, "c"), particle((1100, 1100), 88, "d"), particle((300, 1200), 92, "e")]


def _pair(gap: float) -> Layout:
    return Layout((1500.0, 1500.0), (Body("s1", "particle", (750, 760), 90.0),
                                     Body("s2", "particle", (840 + gap, 760), 90.0)))


def _no_overlap(bodies) -> None:
    for i, a in enumerate(bodies):
        for b in bodies[i + 1:]:
            assert math.dist(a.at, b.at) >= a.radius + b.radius - 1.0, (a.id, b.id)


def test_objects_touching():
    """Two particles in contact image as one aggregate: an obstacle, never pushed; the run
    fills the slots beside it with the others."""
    out = twice(particles_only(AGGREGATE + LONERS), _pair(30.0))
    final = {b.id: b for b in out.report.final_objects}
    assert (final["a"].at, final["b"].at) == ((400.0, 700.0), (490.0, 700.0))
    assert len(out.filled) == 2 and max(out.errors.values()) <= 20.0
    _no_overlap(out.report.final_objects)


def test_objects_touching_in_their_slots():
    """Two slots in contact: one object is pushed against the other. How many fill varies
    with the executor (at one commit the second stopped 23-30 nm short on seeds 1-3, at a
    later one both objects were taken for lost), but nothing overlaps, nothing leaves the
    working area and the error of what was placed stays bounded."""
    out = twice(particles_only(AGGREGATE + LONERS), _pair(0.0))
    assert max(out.errors.values(), default=0.0) <= 40.0
    _no_overlap(out.report.final_objects)
    assert all(0 <= b.at[0] <= 1500 and 0 <= b.at[1] <= 1500 for b in out.report.final_objects)


# -- a slot on a keep-out's boundary -----------------------------------------------------

PAD = Keepout(((500.0, 800.0), (1000.0, 800.0), (1000.0, 1000.0), (500.0, 1000.0)))
ON_PAD = Body("s1", "particle", (750.0, 755.0), 90.0)            # touches the pad from below


def _pad_run(diameter: float, seed: int):
    objs = [particle((300, 300), diameter, "a"), particle((1200, 300), diameter, "b"),
            particle((300, 1200), diameter, "c")]
    return twice(particles_only(objs), Layout((1500.0, 1500.0), (ON_PAD,), (PAD,)), seed=seed)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_slot_on_a_keepout_boundary(seed):
    out = _pad_run(86.0, seed)
    assert out.filled == ("s1",) and out.errors["s1"] <= 20.0
    pad = PAD.geometry()
    for b in out.report.final_objects:                              # nothing entered the keep-out
        assert pad.distance(shapely.Point(b.at)) >= b.radius - 1.0


def test_a_slot_on_a_keepout_boundary_takes_an_object_a_little_larger():
    """An object identified 90.03 nm wide had no path into a 90 nm slot touching a keep-out
    ('no path for o3'); it may now reach up to 1 nm (planner.core.SIZE_SLACK) beyond the
    slot's footprint there, and nothing enters the keep-out by more than that."""
    out = _pad_run(90.0, 2)
    assert out.filled == ("s1",)
    pad = PAD.geometry()
    for b in out.report.final_objects:
        assert pad.distance(shapely.Point(b.at)) >= b.radius - 1.0


# -- drift larger than an object between two scans -----------------------------------------

@pytest.mark.parametrize("strategy", ["kalman", "full"])
def test_drift_larger_than_an_object_between_two_scans(strategy):
    """At 2 nm/s the sample drifts 300 nm during the 150 s full scan and ~60 nm, two thirds
    of a particle, between one push's scans and the next: the filter still fills the slots."""
    scene, layout = family_case("tiny", 2, drift=2.0)
    out = twice(scene, layout, seed=2, strategy=strategy)
    assert out.report.instrument_time.full_scan * 2.0 > 3 * 90.0
    assert len(out.filled) == 2 and max(out.errors.values()) <= 20.0
    blind = outcome(scene, layout, seed=2, strategy="open-loop")[1]
    # blind, the error grows with the drift: at most drift x time plus the pushes' length
    pushed = sum(math.dist(*op.tip_path[i:i + 2]) for op in blind.summary.plan.operations
                 for i in range(len(op.tip_path) - 1))
    assert 100.0 < max(blind.errors.values()) < 2.0 * blind.report.instrument_time.total + pushed


# -- Kalman: nearly singular or huge covariance, long gaps --------------------------------

def _filter_run(P0, gaps, seed=4):
    """A filter fed a constant drift of (0.3, -0.2) nm/s measured with 2 nm noise after each
    gap; returns its estimates and covariances."""
    rng = np.random.default_rng(seed)
    f = DriftFilter(DriftFilterParams(q=1e-6, q_offset=1.0), epoch=0.0, P0=P0)
    v = np.array([0.3, -0.2])
    t, out = 0.0, []
    for gap in gaps:
        t += gap
        for k in range(3):                                   # a burst of three reference scans
            tk = t + 20.0 * k
            f.measure(tk, v * tk + rng.normal(0.0, 2.0, 2), np.eye(2) * 4.0, label=f"o{k}")
        t += 40.0
        est = f.offset(t)
        out.append((t, est.offset.copy(), est.cov.copy(), f.x.copy()))
    return out


@pytest.mark.parametrize("P0", [np.diag([1e12, 1e12, 1e6, 1e6]),                 # huge
                                np.diag([1e-12, 1e-12, 1e-14, 1e-14]),           # nearly singular
                                np.array([[1e8, 1e8 - 1e-3, 0, 0], [1e8 - 1e-3, 1e8, 0, 0],
                                          [0, 0, 1.0, 1.0 - 1e-12], [0, 0, 1.0 - 1e-12, 1.0]])])
def test_nearly_singular_or_huge_kalman_covariance_and_long_gaps(P0):
    gaps = [0.0, 10.0, 1e4, 5.0, 1e6, 1e3]
    run = _filter_run(P0, gaps)
    assert [(t, o.tolist(), c.tolist()) for t, o, c, _ in run] == \
        [(t, o.tolist(), c.tolist()) for t, o, c, _ in _filter_run(P0, gaps)]
    for t, offset, cov, x in run:
        assert no_nan(offset, cov, x)
        assert np.all(np.linalg.eigvalsh(cov) >= -1e-9 * max(1.0, np.abs(cov).max()))
        truth = np.array([0.3, -0.2]) * t
        sigma = math.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0))
        # consistent: within 5 sigma of the truth (errors 0.5-4.9 nm, sigma 1.9 nm, measured)
        assert np.linalg.norm(offset - truth) <= 5 * sigma
    # a confident wrong prior (the nearly singular one: velocity 0 +/- 1e-7 nm/s) is corrected
    assert np.linalg.norm(run[-1][1] - np.array([0.3, -0.2]) * run[-1][0]) < 6.0


# -- DAC quantisation comparable to the tolerance -------------------------------------------

@pytest.mark.parametrize("dac_bits, fills", [(16, 2), (13, 2), (12, 2), (10, 0)])
def test_dac_quantisation_comparable_to_the_tolerance(dac_bits, fills):
    """12 bits over 90 µm: 22 nm per code, more than the 20 nm tolerance; 10 bits: 88 nm.
    The tip lands on the code grid, the scans still see where objects are and corrections
    bring them in: both slots filled down to 12 bits (seed 1); at 10 bits nothing is sure,
    but the error stays within a code of the tolerance."""
    scene, layout = family_case("tiny", 1, drift=0.3)
    scene = dataclasses.replace(scene, params=dataclasses.replace(
        scene.params, scanner=InstrumentConfig(dac_bits=dac_bits)))
    code = 90000.0 / 2 ** dac_bits
    out = twice(scene, layout)
    assert len(out.filled) >= fills
    errors = list(out.errors.values())            # the assigned slots (none may be, at 10 bits)
    assert math.sqrt(sum(e * e for e in errors) / max(len(errors), 1)) <= 20.0 + code


# -- runs long enough for time to lose float precision ------------------------------------

@pytest.mark.parametrize("start", [1.7e9, 1e12])
def test_long_runs_where_time_loses_float_precision(monkeypatch, start):
    """The instrument clock reads ``start`` s when the run begins (an instrument counting
    from its boot or from 1970): at 1e12 s a float64 second has 0.1 ms steps, the DAC's
    sample period is 1 ms. The run must do what it does from 0."""
    scene, layout = family_case("tiny", 3)
    ref = twice(scene, layout, seed=3)
    monkeypatch.setattr(dryrun, "SimulatedAFM", functools.partial(SimulatedAFM, start_time=start))
    late = twice(scene, layout, seed=3)
    assert late.filled == ref.filled
    for t in ref.errors:
        assert late.errors[t] == pytest.approx(ref.errors[t], abs=1.0)
    assert late.report.instrument_time.total == pytest.approx(ref.report.instrument_time.total, rel=1e-3)


# -- identical objects: assignment ties ------------------------------------------------------

def test_identical_objects():
    """Four identical particles placed symmetrically about two slots: every assignment costs
    the same. The run picks one, the same every time, and fills both."""
    c = 750.0
    objs = [particle((c + dx, c + dy), 90.0, f"p{i}") for i, (dx, dy) in
            enumerate([(-400, -300), (400, -300), (-400, 300), (400, 300)])]
    slots = (Body("s1", "particle", (c - 60, c), 90.0), Body("s2", "particle", (c + 60, c), 90.0))
    out = twice(particles_only(objs), Layout((1500.0, 1500.0), slots))
    assert len(out.filled) == 2 and max(out.errors.values()) <= 20.0
    assert len({a.object for a in out.report.assignment}) == 2


# -- the drift carries a push beyond the scanner's range ---------------------------------

def test_a_push_the_drift_carries_beyond_the_scanners_range_is_given_up_not_a_crash():
    """A slot 70 nm from the sample's edge, a scanner 200 nm larger on each side, the
    sample drifting -1.2 nm/s in x: by the time of the push the layout's edge lies beyond
    the scanner's range, and the push's path with it. Nothing of it is sent (the DAC
    path's range check); the object is given up, an obstacle, and the run goes on to fill
    what it can reach (scale1000 seed 1 stopped with InstrumentLimitError after 10 h)."""
    params = dataclasses.replace(EXACT, drift=DriftParams((-1.2, 0.0), 0.1),
                                 scanner=dataclasses.replace(EXACT.scanner, xy_range=(4000.0, 4000.0)))
    scene = Scene((3600.0, 3600.0), (Body("p1", "particle", (400.0, 1800.0), 90.0),
                                     Body("p2", "particle", (2500.0, 1500.0), 90.0)), params=params, seed=1)
    layout = Layout((3600.0, 3600.0), (Body("s1", "particle", (70.0, 1800.0), 90.0),
                                       Body("s2", "particle", (2500.0, 2100.0), 90.0)))
    texts = []
    out = dryrun.dry_run(scene, layout, seed=1, options=ExecOptions(strategy="full"),
                         subscribers=[lambda topic, doc: texts.append(doc.text) if topic == "event" else None])
    assert [c for _, c in out.summary.failures] == ["out of range"]
    assert any("would leave the scanner's range" in t and "nothing sent" in t for t in texts)
    assert out.truly_filled == ("s2",) and out.verdict_filled == ("s2",) and not out.disagreements
