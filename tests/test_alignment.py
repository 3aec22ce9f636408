"""Registration of a layout to the scan by its alignment marks (issue 17): corners, the
transform, its failures in one line, the frame checks, and dry-runs of a layout drawn in
a frame turned and shifted against the scene's."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import shapely
from hypothesis import given
from hypothesis import strategies as st

from nanoasm.bodies import Body
from nanoasm.cad.frame import Similarity, similarity_from_table
from nanoasm.cad.layout import layout_from_dict
from nanoasm.cli import main
from nanoasm.dryrun import dry_run
from nanoasm.errors import InputError
from nanoasm.executor.assembly import Assembly
from nanoasm.executor.engine import RunEngine
from nanoasm.executor.report import report_from_dict
from nanoasm.executor.strategy import ExecOptions
from nanoasm.planner import PlanOptions, plan_assembly, plan_from_dict
from nanoasm.planner.alignment import in_scan_frame, register
from nanoasm.planner.corners import corners
from nanoasm.review import review
from nanoasm.schema import Table
from nanoasm.world.environment import Environment, EnvObject, EnvObstacle
from nanoasm.world.identify import identify
from nanoasm.world.readers import save_height_image
from nanoasm.world.render import make_surface, render_scan
from nanoasm.world.scene import scene_from_dict
from nanoasm.world.sim import SimulatedAFM

AREA = 3000.0
#: Two electrode pads (the right one runs off the area) and an L-shaped marker, in the
#: scene's (the scan's) frame.
PADS = ([[0, 1300], [1200, 1300], [1200, 1700], [0, 1700]],
        [[1800, 1300], [3000, 1300], [3000, 1700], [1800, 1700]],
        [[2300, 2300], [2650, 2300], [2650, 2420], [2420, 2420], [2420, 2650], [2300, 2650]])
SLOTS = ((1400, 1500), (1600, 1500), (1500, 2100))       # scene frame
#: The layout's frame onto the scene's: a few degrees and hundreds of nm.
TURNED = Similarity(4.0, (300.0, -200.0))


def layout_doc(to_scene: Similarity = TURNED, *, slots=SLOTS, position: float = 20.0) -> dict:
    """A layout drawn in its own frame: the scene's slots and pads moved back by ``to_scene``."""
    back = to_scene.inverse()
    return {"format": "nanoasm.layout/1", "name": "chip", "area": [AREA, AREA],
            "tolerance": {"position": position},
            "target": [{"id": f"s{i + 1}", "kind": "particle", "at": list(back.point(p)), "diameter": 90}
                       for i, p in enumerate(slots)],
            "mark": [{"polygon": [list(q) for q in back.polygon(p)]} for p in PADS]}


def scene_doc(pads=PADS) -> dict:
    return {"format": "nanoasm.scene/1", "area": [AREA, AREA], "seed": 5,
            "object": [{"kind": "particle", "at": p, "diameter": 90} for p in
                       ([600, 700], [1500, 800], [2400, 600], [700, 2300], [1500, 2500])],
            "obstacle": [{"polygon": p, "height": 40} for p in pads],
            "drift": {"velocity": [0.2, -0.15], "random_walk": 0.05}}


def scanned(pads=PADS, seed: int = 1):
    """A rendered 10 nm scan of the pads (40 nm high) and two particles."""
    rng = np.random.default_rng(seed)
    bodies = [Body("p1", "particle", (700, 700), 90), Body("p2", "particle", (1500, 2200), 90)]
    return render_scan(make_surface(bodies, [(p, 40.0) for p in pads], (AREA, AREA), rng=rng), 10.0, rng=rng)


@pytest.fixture(scope="module")
def env() -> Environment:
    return identify(scanned())


def error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("nanoasm: error: "), err
    return err[0]


# -- the transform and corners -------------------------------------------------------

@given(rot=st.floats(-180, 180), tx=st.floats(-1e4, 1e4), ty=st.floats(-1e4, 1e4), s=st.floats(0.5, 2.0),
       x=st.floats(-1e4, 1e4), y=st.floats(-1e4, 1e4))
def test_similarity_inverse_undoes_it(rot, tx, ty, s, x, y):
    t = Similarity(rot, (tx, ty), s)
    back = t.inverse().point(t.point((x, y)))
    assert back == pytest.approx((x, y), abs=1e-6 * max(1.0, abs(x), abs(y), abs(tx), abs(ty)))
    assert similarity_from_table(Table(json.loads(json.dumps(t.to_dict())), "p")) == t


def test_similarity_maps_a_rod_slot():
    t = Similarity(30.0, (100.0, -50.0), 1.5)
    rod = t.body(Body("r", "rod", (10.0, 0.0), 20.0, 170.0, 300.0))
    assert rod.at == pytest.approx((100 + 15 * math.cos(math.radians(30)), -50 + 15 * math.sin(math.radians(30))))
    assert (rod.angle, rod.diameter, rod.length) == pytest.approx((20.0, 30.0, 450.0))


@given(w=st.floats(150, 1000), h=st.floats(150, 1000), turn=st.floats(-44, 44),
       grow=st.one_of(st.just(0.0), st.floats(1, 30)))
def test_corners_of_a_grown_rectangle_sit_on_their_miters(w, h, turn, grow):
    t = Similarity(turn, (500.0, 300.0))
    rect = [(0, 0), (w, 0), (w, h), (0, h)]
    grown = shapely.Polygon(t.polygon(rect)).buffer(grow, quad_segs=8)     # rounded, as a tip rounds them
    exact = corners(t.polygon(rect), min_edge=60, max_gap=100)
    found = corners(list(grown.exterior.coords)[:-1], min_edge=60, max_gap=100)
    assert len(exact) == len(found) == 4
    for c in exact:
        moved = np.add(c.at, grow * np.asarray(c.miter))
        assert min(math.dist(moved, f.at) for f in found) < 0.02 * grow + 1e-6
        assert c.turn == pytest.approx(90.0)


def test_an_l_has_a_concave_corner():
    cs = corners([(0, 0), (200, 0), (200, 50), (50, 50), (50, 200), (0, 200)], min_edge=40, max_gap=50)
    concave = [c for c in cs if c.turn < 0]
    assert len(cs) == 6 and len(concave) == 1
    assert concave[0].at == pytest.approx((50, 50)) and concave[0].miter == pytest.approx((1, 1))


# -- registration --------------------------------------------------------------------

@pytest.mark.parametrize("turn, shift", [(4.0, (300.0, -200.0)), (-6.0, (-250.0, 420.0)), (0.0, (0.0, 0.0))])
def test_registration_finds_the_transform(env, turn, shift):
    truth = Similarity(turn, shift)
    layout = layout_from_dict(layout_doc(truth), "chip.toml")
    a = register(layout, env, resolution=10.0, source="chip.toml")
    assert a.transform.rotation == pytest.approx(turn, abs=0.15)
    assert a.transform.translation == pytest.approx(shift, abs=6.0)
    assert a.transform.residual < 10 and a.marks == 3 and a.corners >= 8
    assert 5 < a.grown < 40                         # the tip broadens the 40 nm steps
    for t, p in zip(in_scan_frame(layout, env, source="chip.toml")[0].targets, SLOTS):
        assert math.dist(t.at, p) < 6.0             # every slot where the scene has it


@pytest.mark.parametrize("turn, shift, seed", [(-9.6, (267.4, -218.9), 0), (7.3, (-120.0, 250.0), 1),
                                               (2.5, (40.0, 10.0), 2)])
def test_registration_of_marks_turned_against_the_pixel_grid(turn, shift, seed):
    """The marks' edges run across the scan's rows: their outlines are staircases (a
    turn of -9.6 degrees lost every corner while edges were taken from the raw outline)."""
    truth = Similarity(turn, shift)
    env = identify(scanned([truth.polygon(p) for p in PADS], seed=seed))
    layout = layout_from_dict(layout_doc(Similarity()), "chip.toml")       # the pads as drawn
    a = register(layout, env, resolution=10.0)
    assert a.corners >= 6 and a.transform.residual < 10
    assert max(math.dist(a.transform.point(t.at), truth.point(t.at)) for t in layout.targets) < 6.0


def test_registration_with_the_scale_free(env):
    truth = Similarity(3.0, (120.0, 80.0), 1.02)
    a = register(layout_from_dict(layout_doc(truth), "chip.toml"), env, scale=True)
    assert a.transform.scale == pytest.approx(1.02, abs=0.004)
    assert a.transform.rotation == pytest.approx(3.0, abs=0.15)


def test_too_few_marks_found_is_one_line(env):
    far = Similarity(0.0, (0.0, 0.0))
    doc = layout_doc(far)
    doc["mark"] = [{"polygon": [[100, 100], [400, 100], [400, 250], [100, 250]]}]   # nothing there
    with pytest.raises(InputError, match=r"^chip.toml: mark: too few marks found: "):
        register(layout_from_dict(doc, "chip.toml"), env, source="chip.toml")
    with pytest.raises(InputError, match="too few marks found"):
        register(layout_from_dict(layout_doc(), "chip.toml"), Environment((AREA, AREA)), source="chip.toml")


def test_a_residual_above_the_tolerance_is_refused(env):
    with pytest.raises(InputError, match=r"^chip.toml: mark: registration residual .* above the layout's "
                                         r"position tolerance 2 nm"):
        register(layout_from_dict(layout_doc(position=2.0), "chip.toml"), env, source="chip.toml")


def test_a_mark_seen_twice_is_ambiguous():
    ell = PADS[2]
    other = [[x - 1700, y - 1800] for x, y in ell]          # the same marker again, elsewhere
    env = identify(scanned((ell, other), seed=2))
    doc = layout_doc(Similarity(2.0, (50.0, 30.0)), slots=((1500, 1500),))
    doc["mark"] = doc["mark"][2:]                           # the layout knows one marker
    with pytest.raises(InputError, match=r"^chip.toml: mark: ambiguous match: "):
        register(layout_from_dict(doc, "chip.toml"), env, source="chip.toml")


def test_no_marks_or_no_align_keeps_the_frame(env):
    layout = layout_from_dict(layout_doc(), "chip.toml")
    same, alignment = in_scan_frame(layout, env, "none")
    assert same is layout and alignment is None


# -- frame checks --------------------------------------------------------------------

def test_slots_outside_the_scan_are_refused(tmp_path, capsys):
    layout = tmp_path / "big.json"
    layout.write_text(json.dumps({"format": "nanoasm.layout/1", "area": [3000, 3000], "target": [
        {"kind": "particle", "at": [1500, 1500], "diameter": 90}, {"kind": "particle", "at": [200, 200],
                                                                    "diameter": 90}]}))
    env = tmp_path / "env.json"
    Environment((500.0, 500.0), (EnvObject("o1", "particle", (250.0, 250.0), 90.0),)).save(env)
    plan = tmp_path / "plan.json"
    assert main(["plan", str(layout), "--env", str(env), "-o", str(plan)]) == 1
    line = error_line(capsys)
    assert line.startswith(f"nanoasm: error: {layout}: target: 1 of 2 slot(s) lie outside the scanned area "
                           "500 x 500 nm") and "t1" in line
    assert not plan.exists()


def test_a_slot_on_an_obstacle_is_named():
    layout = layout_from_dict({"format": "nanoasm.layout/1", "area": [3000, 3000], "target": [
        {"id": "a", "kind": "particle", "at": [1000, 1000], "diameter": 90},
        {"id": "b", "kind": "particle", "at": [2000, 2000], "diameter": 90}]}, "l")
    env = Environment((3000.0, 3000.0), (EnvObject("o1", "particle", (500.0, 500.0), 90.0),
                                         EnvObject("o2", "particle", (2500.0, 500.0), 90.0)),
                      (EnvObstacle(((1800.0, 1800.0), (2300.0, 1800.0), (2300.0, 2200.0), (1800.0, 2200.0)), 30.0),))
    plan, _ = plan_assembly(layout, env)
    assert [a.target for a in plan.assignment] == ["a"]
    (u,) = plan.unfilled
    assert u.target == "b" and u.reason.startswith("slot lies on an identified obstacle (obstacles[1]: 30 nm high")


# -- plan, dry-run, run log, resume --------------------------------------------------

def test_plan_registers_and_carries_the_transform(tmp_path, capsys):
    scan, layout, plan = tmp_path / "scan.npz", tmp_path / "chip.json", tmp_path / "plan.json"
    save_height_image(scanned(), scan)
    layout.write_text(json.dumps(layout_doc()))
    assert main(["plan", str(layout), "--scan", str(scan), "-o", str(plan)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("nanoasm: registered the layout to the scan: rotation ")
    assert "3 of 3 mark(s) found" in err[0]
    reg = plan_from_dict(json.loads(plan.read_text())).registration
    assert reg.rotation == pytest.approx(4.0, abs=0.15) and reg.translation == pytest.approx((300, -200), abs=6)
    assert main(["plan", str(layout), "--scan", str(scan), "-o", str(plan), "--no-align"]) == 0
    assert "registration" not in json.loads(plan.read_text())
    assert main(["plan", str(layout), "--scan", str(scan), "-o", str(plan), "--no-align", "--align-scale"]) == 1
    assert "--align-scale: does not go with --no-align" in error_line(capsys)


@pytest.fixture(scope="module")
def turned_run(tmp_path_factory):
    """A dry-run of the layout drawn turned by 4 degrees and shifted by (300, -200) nm."""
    scene = scene_from_dict(scene_doc(), "scene")
    layout = layout_from_dict(layout_doc(), "chip.toml")
    return scene, layout, dry_run(scene, layout, seed=5, plan_options=PlanOptions(seed=5), layout_name="chip.toml")


def test_a_turned_and_shifted_layout_is_filled(turned_run):
    scene, layout, out = turned_run
    assert out.truly_filled == ("s1", "s2", "s3") and out.verdict_filled == ("s1", "s2", "s3")
    reg = out.report.registration
    assert reg.rotation == pytest.approx(4.0, abs=0.2) and reg.translation == pytest.approx((300, -200), abs=8)
    doc = json.loads(out.report.dumps())
    assert report_from_dict(doc).registration == reg
    # the report is in the layout's own frame: its slots and the truth where the layout has them
    assert [t.at for t in out.report.targets] == [t.at for t in layout.targets]
    final = {b.id: b for b in out.report.final_objects}
    for a in out.report.assignment:
        assert math.dist(final[a.object].at, layout.target(a.target).at) < layout.tolerance.position


def test_the_report_of_a_layout_without_marks_has_no_registration():
    scene = scene_from_dict(scene_doc(), "scene")
    plain = layout_doc(Similarity())
    plain["keepout"] = plain.pop("mark")
    out = dry_run(scene, layout_from_dict(plain, "l"), seed=5, plan_options=PlanOptions(seed=5))
    assert "registration" not in json.loads(out.report.dumps()) and out.truly_filled == ("s1", "s2", "s3")


def test_a_registered_run_resumed_from_a_checkpoint_ends_as_the_run_that_was_not_stopped():
    scene = scene_from_dict(scene_doc(), "scene")
    layout = layout_from_dict(layout_doc(), "chip.toml")
    sim = SimulatedAFM(scene, seed=5)
    kept: dict = {}

    def keep(topic: str, doc) -> None:
        if topic in ("environment", "plan") and topic not in kept:
            kept[topic] = json.loads(json.dumps(doc))
        if topic == "checkpoint":
            kept["n"] = kept.get("n", 0) + 1
            if kept["n"] == 2:
                kept["state"] = {**json.loads(json.dumps(doc)), "env": kept["environment"],
                                 "first_plan": kept["plan"]}
                kept["sim"] = json.dumps(sim.state_dict(), allow_nan=False)

    whole = RunEngine(sim, [keep]).run(Assembly(layout, ExecOptions()).procedure(sim.config))
    assert "registration" in kept["plan"] and whole.registration is not None
    sim2 = SimulatedAFM.from_state(scene, json.loads(kept["sim"]))
    asm = Assembly(layout, ExecOptions())
    resumed = RunEngine(sim2, []).run(asm.resume(sim2.config, kept["state"]))
    assert asm.layout.registration == whole.registration         # the scan's frame again, from the plan
    assert resumed.counts == whole.counts and resumed.assignment == whole.assignment
    assert {b.id: b.at for b in sim2.truth()} == {b.id: b.at for b in sim.truth()}     # bit for bit
    assert [v.state for v in resumed.slots] == [v.state for v in whole.slots] == ["filled"] * 3


def test_review_maps_the_layout_into_the_logs_frame(tmp_path, capsys):
    scene, layout = tmp_path / "scene.json", tmp_path / "chip.json"
    scene.write_text(json.dumps(scene_doc()))
    layout.write_text(json.dumps(layout_doc()))
    log = tmp_path / "run.mcap"
    assert main(["dry-run", str(scene), str(layout), "--seed", "5", "--log", str(log)]) == 0
    err = capsys.readouterr().err
    assert err.count("nanoasm: registered the layout to the scan: rotation ") == 1
    rev = review(log)
    assert rev.filled == 3 and rev.source == "simulated truth"
    assert rev.layout.registration is not None and all(r.error < 20 for r in rev.slots)
    # Foxglove's /layout: the chip's frame at the start, then where the run has the slots
    from nanoasm.executor.logread import read_log

    first, *later = read_log(log).topic("/layout")
    assert len(later) == 1
    drawn = {e.id: e.texts[0].pose.position for e in later[0].data.entities if e.id.startswith("slot:")}
    chip = {e.id: e.texts[0].pose.position for e in first.data.entities if e.id.startswith("slot:")}
    for i, p in enumerate(SLOTS):
        assert math.dist((drawn[f"slot:s{i + 1}"].x, drawn[f"slot:s{i + 1}"].y), p) < 20
        assert math.dist((chip[f"slot:s{i + 1}"].x, chip[f"slot:s{i + 1}"].y), p) > 100
