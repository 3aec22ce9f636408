"""The simulated AFM: an Instrument whose pushes follow the seed's physics (ch. 3-4)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from nanoasm.instrument import Instrument, InstrumentConfig
from nanoasm.world.params import AdhesionParams, DriftParams, PushParams
from nanoasm.world.pivot import RodPose, pivot_position, rod_step
from simkit import EXACT, particle, path_codes, preload_offset, push, rod, world

from nanoasm.bodies import Body
from nanoasm.errors import InstrumentLimitError


def test_is_an_instrument():
    sim = world([particle((2000, 2000))])
    assert isinstance(sim, Instrument)
    assert sim.config == InstrumentConfig()
    np.testing.assert_array_equal(sim.position(), sim.config.rest_codes())


def test_particle_pushed_straight_moves_the_push_length_minus_the_contact_offset():
    sim = world([particle((2000, 2000), d=50)])
    block, codes = push(sim, (1800, 2000), (2400, 2000))
    (p,) = sim.truth()
    rc = 25 + sim.params.tip.radius
    # the centre ends one contact radius ahead of the tip: moved by 600 - (2000 - rc - 1800)
    assert p.at[0] - 2000 == pytest.approx(600 - (200 - rc), abs=2.0)
    assert p.at[1] == pytest.approx(2000, abs=1.0)
    assert len(block) == len(codes) and np.all(np.diff(block.t) > 0)


def test_particle_direction_scatters_by_the_path_scatter():
    errors = []
    for seed in range(24):
        params = dataclasses.replace(EXACT, push=PushParams(pivot_scatter=0.0, path_scatter=2.0))
        sim = world([particle((2000, 2000), d=50)], params=params, seed=seed)
        push(sim, (1900, 2000), (2200, 2000))
        (p,) = sim.truth()
        dx, dy = p.at[0] - 2000, p.at[1] - 2000
        assert math.hypot(dx, dy) == pytest.approx(300 - 65, abs=12.0)   # less as it slides round
        errors.append(math.degrees(math.atan2(dy, dx)))
    assert 1.0 < np.std(errors) < 3.2


def _slip_world(preload: float):
    params = dataclasses.replace(EXACT, scanner=InstrumentConfig(preload=preload),
                                 adhesion=AdhesionParams(scatter=0.0),
                                 friction=dataclasses.replace(EXACT.friction, scatter=0.0))
    return world([particle((2000, 2000), d=100)], params=params)


def test_preload_below_min_normal_force_slips_over_and_the_object_stays():
    # d = 100 nm: F_os^a = 85.5 nN, F̄z = 3.4 nN (eq. 4.7) > k * 20 nm = 2.4 nN
    sim = _slip_world(20.0)
    block, _ = push(sim, (1850, 2000), (2200, 2000))
    assert sim.truth() == sim.scene.objects
    assert sim.diagnostics()["slips"] == 1
    contact = block.s_n[block.s_n > 0.9]
    level = np.median(contact)
    assert level == pytest.approx(0.8 + 20 / 89, abs=0.03)          # A + preload / K_n
    peak = int(np.argmax(block.s_n))
    assert block.s_n[peak] - level > 0.8                              # riding over the top
    after = block.s_n[peak:][block.s_n[peak:] > 0.9]
    assert np.median(after[-200:]) == pytest.approx(level, abs=0.03)  # collapses back
    # with the default preload the same particle moves
    sim = _slip_world(100.0)
    push(sim, (1850, 2000), (2200, 2000))
    assert sim.truth()[0].at[0] > 2100


def test_lateral_signal_shows_the_pushing_force():
    sim = world([particle((2000, 2000), d=50)])
    block, _ = push(sim, (2000, 1800), (2000, 2300))        # along y: S_l sees F_y (ψ = 0)
    free = world([])
    ref, _ = push(free, (2000, 1800), (2000, 2300))
    assert sim.truth()[0].at[1] > 2250
    pushing = slice(len(ref) - 1000, len(ref) - 10)                  # the last 200 nm of the push
    extra = np.median(block.s_l[pushing]) - np.median(ref.s_l[pushing])
    assert extra == pytest.approx(14.0 / 37.8, rel=0.25)             # ~14 nN of eq. 4.4 at 37.8 nN/V
    assert np.percentile(block.s_l[pushing], 5) > np.median(ref.s_l[pushing]) + 0.2   # held steadily


def test_rod_pushed_near_an_end_turns_about_the_pivot_of_eq_4_10():
    L, x_tip = 500.0, 1800.0                                # push point l = 50 nm from end A
    sim = world([rod((2000, 2000), 0.0, L)])
    push(sim, (x_tip, 1900), (x_tip, 2100))
    (r,) = sim.truth()
    pose, tip = RodPose(2000.0, 2000.0, 0.0, L, 50.0), (x_tip, 1900.0)
    for _ in range(2000):
        pose = rod_step(pose, tip, (0.0, 0.1), tip_radius=10.0).pose
        tip = (tip[0], tip[1] + 0.1)
    assert r.angle == pytest.approx(pose.angle, abs=0.3)
    assert r.at == pytest.approx((pose.x, pose.y), abs=2.0)
    assert r.angle < -10                                     # turned clockwise, pivot near B


def test_first_rotation_centre_is_the_pivot_of_eq_4_10():
    L = 500.0
    sim = world([rod((2000, 2000), 0.0, L)])
    push(sim, (1800, 1900), (1800, 1985))                   # 20 nm beyond first contact (y = 1965)
    (r,) = sim.truth()
    beta = math.radians(r.angle)
    c0, c1 = np.array([2000.0, 2000.0]), np.array(r.at)
    rot = np.array([[math.cos(beta), -math.sin(beta)], [math.sin(beta), math.cos(beta)]])
    fixed = np.linalg.solve(np.eye(2) - rot, c1 - rot @ c0)  # the rigid motion's fixed point
    s = float(pivot_position(50.0, L))                        # eq. 4.10: 370 nm from end A
    assert fixed[0] - (2000 - L / 2) == pytest.approx(s, abs=8.0)
    assert fixed[1] == pytest.approx(2000, abs=3.0)


def test_rod_pushed_at_its_middle_turns_either_way():
    params = dataclasses.replace(EXACT, adhesion=AdhesionParams(object_ratio=5.0))
    senses = set()
    for seed in range(12):
        sim = world([rod((2000, 2000), 0.0, 500.0)], params=params, seed=seed)
        push(sim, (2000, 1900), (2000, 2010))
        senses.add(np.sign(sim.truth()[0].angle))
    assert senses == {-1.0, 1.0}


def test_wire_bends_rather_than_turning():
    L, d = 1600.0, 40.0                                      # σ = 40: a soft wire
    wire = Body("w1", "rod", (2000.0, 2000.0), d, 0.0, L)
    sim = world([wire])
    push(sim, (1400, 1900), (1400, 2200))                    # near end A
    (w,) = sim.truth()
    pose, tip = RodPose(2000.0, 2000.0, 0.0, L, d), (1400.0, 1900.0)
    for _ in range(3000):
        pose = rod_step(pose, tip, (0.0, 0.1), tip_radius=10.0).pose
        tip = (tip[0], tip[1] + 0.1)
    assert w.length < L - 40.0                               # its chord shrank: bent
    assert abs(w.angle) < 0.5 * abs(pose.angle)              # a rigid rod would turn further
    seg = [b for b in sim.footprints() if b.id.startswith("w1#")]
    assert sum(b.length - d for b in seg) == pytest.approx(L - d, rel=1e-6)   # inextensible


def test_objects_not_touched_do_not_move():
    objs = [particle((2000, 2000), id="a"), particle((3500, 3500), id="b"), rod((500, 3500), 30, 400, id="c")]
    sim = world(objs)
    push(sim, (1800, 2000), (2300, 2000))
    after = sim.truth()
    assert after[1] is objs[1] and after[2] is objs[2]
    assert after[0].at[0] > 2300


def test_pushed_particle_shoves_a_neighbour_without_overlap():
    objs = [particle((2000, 2000), id="a"), particle((2052, 2000), id="b")]
    sim = world(objs)
    push(sim, (1800, 2000), (2300, 2000))
    a, b = sim.truth()
    assert b.at[0] > 2300
    assert math.dist(a.at, b.at) >= 50 - 1e-6


def test_signals_in_contact_show_the_preload_and_lifted_the_baseline():
    sim = world([])
    block, _ = push(sim, (1000, 1000), (1500, 1000))
    cfg, c = sim.config, sim.params.cantilever
    in_contact = block.s_n[len(block) // 2]
    assert in_contact == pytest.approx(c.reflection_n + cfg.preload / c.K_n, abs=0.03)
    assert block.s_n[-1] == pytest.approx(c.reflection_n * math.exp(-cfg.lift / 1000), abs=0.03)
    assert sim.signals() == (block.s_n[-1], block.s_l[-1])
    assert np.all(np.isfinite(block.s_n)) and np.all(np.isfinite(block.s_l))


def test_tip_under_preload_sits_off_the_piezo_by_the_deflection():
    off = preload_offset(world([]))
    assert off == pytest.approx((-23.0 * 100 / 89, 0.0), abs=1e-9)   # C2 S̄n along -x at ψ = 0
    sim = world([particle((2000, 2000), d=50)])
    push(sim, (1800, 2000), (2400, 2000), compensate=False)          # tip trails the piezo
    assert sim.truth()[0].at[0] == pytest.approx(2400 + off[0] + 35, abs=2.0)


def test_drift_shows_between_two_scans():
    params = dataclasses.replace(EXACT, drift=DriftParams(velocity=(1.0, 0.0), random_walk=0.0))
    sim = world([particle((1000, 1000), d=60)], area=(2000, 2000), params=params)
    first, second = sim.full_scan(128), sim.full_scan(128)
    shift = _centroid(second) - _centroid(first)
    assert shift == pytest.approx((128.0, 0.0), abs=3.0)            # 128 s of drift per frame
    row = 1000 / (2000 / 128) - 0.5                                   # the particle's row, 1 s per line
    assert _centroid(first) == pytest.approx((1000 + row, 1000), abs=3.0)


def _centroid(image):
    h = image.height
    x, y = image.pixel_centres()
    w = np.where(h > 0.5 * h.max(), h, 0.0)
    return np.array([(w.sum(axis=0) * x).sum() / w.sum(), (w.sum(axis=1) * y).sum() / w.sum()])


def test_scan_line_sees_the_object_and_is_charged_as_a_local_scan():
    sim = world([particle((1000, 1000), d=50)], area=(2000, 2000))
    before = sim.ledger()["local_scan"]
    z = sim.scan_line((900.0, 1000.0), (1100.0, 1000.0), 201)
    assert z.shape == (201,)
    assert z.max() == pytest.approx(50.0, abs=1.5) and abs(int(np.argmax(z)) - 100) <= 2
    t = sim.params.timing
    assert sim.ledger()["local_scan"] - before == pytest.approx(t.scan_line_overhead + 201 * t.scan_line_sample)


def test_clock_charges_minutes_per_frame_and_the_ledger_adds_up():
    sim = world([particle((2000, 2000))])
    sim.full_scan(512)
    assert sim.ledger()["full_scan"] == pytest.approx(512 * sim.params.timing.full_scan_line)
    assert 5 * 60 < sim.clock() < 15 * 60
    push(sim, (1800, 2000), (2300, 2000))
    sim.scan_line((1000.0, 1000.0), (1500.0, 1000.0), 128)
    sim.park()
    ledger = sim.ledger()
    assert ledger["total"] == pytest.approx(sum(v for k, v in ledger.items() if k != "total"), abs=1e-9)
    assert ledger["total"] == pytest.approx(sim.clock(), abs=1e-9)
    assert ledger["push"] > 500 / sim.params.timing.push_speed and ledger["travel"] > 0


def test_park_is_safe_from_any_state_and_repeatedly():
    sim = world([particle((2000, 2000))])
    sim.park()                                            # already at rest: nothing to do
    assert sim.clock() == 0.0
    cfg = sim.config
    sim.write(path_codes(sim, [(1900, 2000, cfg.lift), (1900, 2000, -cfg.preload), (1990, 2000, -cfg.preload)]))
    sim.park()                                            # from contact, touching a particle
    np.testing.assert_array_equal(sim.position(), cfg.rest_codes())
    t = sim.clock()
    sim.park()
    assert sim.clock() == t
    assert all(math.isfinite(v) for v in sim.signals())
    sim.full_scan(32)
    sim.park()
    np.testing.assert_array_equal(sim.position(), cfg.rest_codes())


def test_a_refused_chunk_changes_nothing():
    sim = world([particle((2000, 2000))])
    bad = np.vstack([sim.position(), sim.position() + [5000, 0, 0]])
    with pytest.raises(InstrumentLimitError):
        sim.write(bad)
    assert sim.clock() == 0.0
    np.testing.assert_array_equal(sim.position(), sim.config.rest_codes())


def test_same_seed_same_commands_same_run():
    def run():
        sim = world([particle((2000, 2000)), rod((2600, 2000), 90, 400, id="r")],
                    params=dataclasses.replace(EXACT, push=PushParams()), seed=7)
        block, _ = push(sim, (1800, 2000), (2300, 2000))
        return block, sim.truth(), sim.full_scan(64).height
    (b1, t1, h1), (b2, t2, h2) = run(), run()
    np.testing.assert_array_equal(b1.s_n, b2.s_n)
    np.testing.assert_array_equal(b1.s_l, b2.s_l)
    np.testing.assert_array_equal(h1, h2)
    assert t1 == t2


def test_truth_reports_rods_with_angle_and_length():
    sim = world([rod((2000, 2000), 30.0, 400.0)])
    (r,) = sim.truth()
    assert (r.kind, r.angle, r.length, r.id) == ("rod", 30.0, 400.0, "r1")


def test_scene_larger_than_the_scanner_is_refused():
    with pytest.raises(ValueError, match="exceeds the scanner"):
        world([], area=(100000.0, 1000.0))


@pytest.mark.parametrize("angle", [0.0, 30.0, 45.0, 135.0, -45.0, -90.0])
def test_a_push_in_any_direction_carries_the_particle(angle):
    """A DAC draws a diagonal as a staircase of single-axis code steps; the particle must
    follow the path, not each stair."""
    import math

    sim = world([particle((2000.0, 2000.0), d=90.0)])
    u = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    rc = 45.0 + sim.params.tip.radius
    start = np.array([2000.0, 2000.0]) - u * (rc + 20.0)
    push(sim, start, start + u * 620.0)
    (p,) = sim.truth()
    moved = np.array(p.at) - 2000.0
    assert float(moved @ u) == pytest.approx(600.0 - 20.0, abs=25.0)
    assert abs(float(moved @ np.array([-u[1], u[0]]))) < 25.0


def test_by_default_the_scene_sits_centred_in_the_scanner_range():
    from nanoasm.world.scene import Scene
    from nanoasm.world.sim import SimulatedAFM

    scene = Scene((4000.0, 4000.0), (particle((1000.0, 3000.0), d=80.0),), (), EXACT, 1)
    sim = SimulatedAFM(scene)
    px, py = sim.placement
    assert (px, py) == pytest.approx(((90000 - 4000) / 2, (90000 - 4000) / 2))
    line = sim.scan_line((px + 800.0, py + 3000.0), (px + 1200.0, py + 3000.0), 401)
    assert abs(int(np.argmax(line)) - 200) <= 2           # the particle is under px + 1000


def test_the_sim_table_reaches_the_simulator():
    from nanoasm.world.scene import scene_from_dict
    from nanoasm.world.sim import SimulatedAFM

    scene = scene_from_dict({"format": "nanoasm.scene/1", "area": [2000, 2000],
                             "object": [{"kind": "particle", "at": [1000, 1000], "diameter": 80}],
                             "sim": {"capture_angle": 30, "piezo_tau": 0.01, "roughness_rms": 0.0},
                             "faults": {"lost_min": 100, "lost_max": 200}}, "s.toml")
    sim = SimulatedAFM(scene)
    assert sim._world.sim.capture_angle == 30 and sim.params.sim.piezo_tau == 0.01
    assert sim.params.faults.lost_max == 200
    line = sim.scan_line((sim.placement[0] + 100.0, sim.placement[1] + 100.0),
                         (sim.placement[0] + 600.0, sim.placement[1] + 100.0), 101)
    # no roughness: only the 0.3 nm height noise is left on bare substrate
    assert float(np.std(line)) < 0.5
