"""Running what you reviewed: ``--plan`` executes a plan made by ``nanoasm plan`` (or
refuses when the scene changed since), and ``--region``/``--pixels`` set the full scan."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import pytest

from nanoasm.cad.layout import load_layout
from nanoasm.cli import main
from nanoasm.errors import InputError
from nanoasm.examples import path as example
from nanoasm.executor.logread import read_log
from nanoasm.executor.report import load_report
from nanoasm.executor.reviewed_plan import ReviewedPlan, load_reviewed, offset, planned_objects
from nanoasm.executor.scan_attachment import FULL_SCAN_ATTACHMENT, full_scan_image
from nanoasm.planner import PlanOptions
from nanoasm.planner.core import plan_assembly
from nanoasm.planner.plan import load_plan
from nanoasm.world.environment import Environment, EnvObject
from nanoasm.world.scene import load_scene

SCENE, LAYOUT = example("particles_scene.toml"), example("particles.toml")
#: o2 is the particle a run of the bundled scene plans into s1 itself: a plan made without
#: it assigns other particles, so a run that follows the plan is told from one that plans
LEFT_OUT = "o2"


def scene_env(scene_file, leave_out=()) -> Environment:
    """The scene's objects as a drift-free identification of its full scan would give them
    (the dry-run's layout frame is the scene's at its start), ids kept."""
    scene = load_scene(scene_file)
    return Environment(scene.area, tuple(EnvObject(o.id, o.kind, o.at, o.diameter, o.angle, o.length)
                                         for o in scene.objects if o.id not in leave_out))


def error_lines(err: str) -> list[str]:
    assert "Traceback" not in err
    return [line for line in err.strip().splitlines() if line.startswith("nanoasm: error: ")]


@pytest.fixture(scope="module")
def reviewed(tmp_path_factory):
    """``nanoasm plan`` of the bundled particles layout on its scene, o2 left out."""
    d = tmp_path_factory.mktemp("reviewed")
    env, plan = d / "env.json", d / "plan.json"
    scene_env(SCENE, (LEFT_OUT,)).save(env)
    assert main(["plan", str(LAYOUT), "--env", str(env), "-o", str(plan)]) == 0
    return plan


def test_a_dry_run_executes_the_reviewed_plan(reviewed, tmp_path, capsys):
    plan = load_plan(reviewed)
    report, log = tmp_path / "r.json", tmp_path / "run.mcap"
    code = main(["dry-run", str(SCENE), str(LAYOUT), "--plan", str(reviewed), "--report", str(report),
                 "--log", str(log)])
    capsys.readouterr()
    assert code == 0
    rep = load_report(report)
    # the plan's assignment (the report names the scene's objects, as the plan does), not
    # the run's own, which takes o2 into a slot
    assert rep.assignment == plan.assignment and LEFT_OUT not in {a.object for a in rep.assignment}
    # the plan's pushes; pushes that cannot touch one another may be made together, in
    # another order (contact_batch, executor/batching.py)
    order = list(dict.fromkeys(op.object for op in plan.operations))
    assert rep.counts.replans == 0 and sorted(rep.pushed) == sorted(order)
    assert rep.plan == str(reviewed) and json.loads(report.read_text())["plan"] == str(reviewed)
    assert [v.state for v in rep.slots] == ["filled"] * 4
    # the run log says so, and its first plan is the reviewed one, in the run's ids
    contents = read_log(log)
    assert contents.metadata["nanoasm"]["plan"] == str(reviewed)
    first = contents.topic("/plan")[0].data
    assert [op["tip_path"] for op in first["operations"]] == [[list(p) for p in op.tip_path]
                                                              for op in plan.operations]
    assert any(m.data.message.startswith(f"plan: the reviewed plan {reviewed}: 4 slot(s) assigned")
               for m in contents.topic("/events"))


def test_a_moved_object_refuses_the_plan_and_nothing_is_pushed(reviewed, tmp_path, capsys):
    plan = load_plan(reviewed)
    moved = plan.assignment[0].object
    scene = load_scene(SCENE)
    at = next(o.at for o in scene.objects if o.id == moved)
    text = SCENE.read_text()
    old = f"at = [{at[0]!r}, {at[1]!r}]"
    assert text.count(old) == 1
    changed = tmp_path / "moved.toml"
    changed.write_text(text.replace(old, f"at = [{round(at[0] + 200.0, 3)!r}, {at[1]!r}]"))
    report, log = tmp_path / "r.json", tmp_path / "run.mcap"
    code = main(["dry-run", str(changed), str(LAYOUT), "--plan", str(reviewed), "--report", str(report),
                 "--log", str(log)])
    err = capsys.readouterr().err
    assert code == 1 and not report.exists()
    (line,) = error_lines(err)
    assert err.strip().splitlines()[-1] == line
    assert re.fullmatch(rf"nanoasm: error: {re.escape(str(reviewed))}: object {moved} moved (19\d|20\d) nm since "
                        r"the plan \(limit 30 nm\); plan again", line), line
    topics = {m.topic for m in read_log(log).messages}
    assert "/push" not in topics and "/dac" not in topics and "/plan" not in topics


def test_region_and_pixels_set_the_full_scan(tmp_path, capsys):
    report, log = tmp_path / "r.json", tmp_path / "run.mcap"
    code = main(["dry-run", str(SCENE), str(LAYOUT), "--region", "42500", "42500", "47500", "47000",
                 "--pixels", "250", "--report", str(report), "--log", str(log)])
    capsys.readouterr()
    assert code == 0
    image = full_scan_image(read_log(log).attachments[FULL_SCAN_ATTACHMENT])
    # the square on the region's longer side, 5000 nm at 20 nm a pixel (by default 400 x 400 px of 4000 nm)
    assert image.height.shape == (250, 250) and image.pixel_size == pytest.approx(20.0)
    line_time = load_scene(SCENE).params.timing.full_scan_line
    assert load_report(report).instrument_time.full_scan == pytest.approx(250 * line_time)
    assert read_log(log).metadata["nanoasm"]["full_scan"] == "region 42500 42500 47500 47500 nm, 250 pixels a side"


@pytest.mark.parametrize("args, words", [
    (["--region", "43000", "43000", "42000", "47000"], "--region: must have a positive size (X1 > X0 and Y1 > Y0)"),
    (["--region", "88000", "43000", "92000", "47000"], "--region: the full scan, the 4000 nm square at (88000, "
                                                       "43000), leaves the scanner's XY range 0..90000 x 0..90000 nm"),
    (["--region", "43000", "43000", "45000", "45000"], "--region: the 2000 nm square does not hold the layout's area"),
    (["--region", "0", "0", "50000", "50000"], "--region: a 50000 nm square at 10 nm a pixel needs 5000 pixels"),
    (["--pixels", "8"], "--pixels: must be from 16 to 4096 pixels a side, got 8"),
    (["--pixels", "60"], "--pixels: 60 pixels over 4000 nm are 66.7 nm each, too coarse for the layout's 90 nm"),
    (["--contact-batch", "0"], "--contact-batch: must be"),
    (["--contact-batch", "65"], "--contact-batch: must be"),
])
def test_a_bad_region_or_pixel_count_is_one_line(args, words, tmp_path, capsys):
    report = tmp_path / "r.json"
    code = main(["dry-run", str(SCENE), str(LAYOUT), *args, "--report", str(report)])
    err = capsys.readouterr().err
    (line,) = err.strip().splitlines()
    assert code == 1 and line.startswith(f"nanoasm: error: {words}"), line
    assert not report.exists()


def test_run_checks_plan_and_region_before_the_instrument(reviewed, tmp_path, capsys):
    inst = example("instrument_ni.toml")
    code = main(["run", str(LAYOUT), "--instrument", str(inst), "--region", "89000", "0", "93000", "4000"])
    assert code == 1 and error_lines(capsys.readouterr().err)[0].startswith("nanoasm: error: --region: the full scan")
    other = tmp_path / "other.json"
    other.write_text(reviewed.read_text().replace('"sparse-2"', '"bowtie"'))
    code = main(["run", str(LAYOUT), "--instrument", str(inst), "--plan", str(other)])
    (line,) = error_lines(capsys.readouterr().err)
    assert code == 1 and line == (f"nanoasm: error: {other}: made for layout 'bowtie', not 'sparse-2' ({LAYOUT}); "
                                  "plan again")
    code = main(["dry-run", "--resume", str(tmp_path / "x.mcap"), "--plan", str(reviewed)])
    (line,) = error_lines(capsys.readouterr().err)
    assert code == 1 and line.startswith("nanoasm: error: --plan: shapes how a run starts")
    code = main(["run", "--instrument", str(inst), "--resume", str(tmp_path / "x.mcap"), "--contact-batch", "2"])
    (line,) = error_lines(capsys.readouterr().err)
    assert code == 1 and line.startswith("nanoasm: error: --contact-batch: shapes how a run starts")


def test_a_plan_for_other_slots_is_refused_before_the_run(reviewed, tmp_path):
    layout = load_layout(LAYOUT)
    moved = replace(layout, targets=(replace(layout.targets[0], at=(2175.0, 2075.0)), *layout.targets[1:]))
    with pytest.raises(InputError, match=r"slot s1 is at \(2175, 2075\) in chip.toml, and the plan takes o\d+ to "
                                         r"\(2075, 2075\); plan again"):
        load_reviewed(reviewed, moved, "chip.toml", "rigid")
    fewer = replace(layout, targets=layout.targets[:3])
    with pytest.raises(InputError, match=r"its slots are not those of chip.toml \(s4 not in it\); plan again"):
        load_reviewed(reviewed, fewer, "chip.toml", "rigid")


def test_where_the_plan_had_its_objects_is_read_from_its_pushes():
    """A particle's first push starts where the planner put the tip behind it; a rod's
    first push lands it, under the pivot model, where the plan expects: both 0 nm off
    on the environment the plan was made from."""
    options = PlanOptions()
    for scene, layout in ((SCENE, LAYOUT), (example("rods_scene.toml"), example("rods.toml"))):
        env, layout = scene_env(scene), load_layout(layout)
        plan, _ = plan_assembly(layout, env, options)
        planned = planned_objects(plan, layout, options)
        assert {p.kind for p in planned.values() if not p.stays} == {t.kind for t in layout.targets}
        for p in planned.values():
            if not p.stays:
                assert offset(p, env.object(p.id), options) < 1e-6, p.id


def test_gone_and_in_the_way_are_named(reviewed):
    layout = load_layout(LAYOUT)
    plan = load_plan(reviewed)
    env = scene_env(SCENE)
    first = plan.operations[0]
    rv = ReviewedPlan(plan, "plan.json")
    adopted, line = rv.adopt(layout, env, 10.0, PlanOptions())
    assert adopted.assignment == plan.assignment and line.startswith("plan: the reviewed plan plan.json: 4 slot(s)")
    gone = replace(env, objects=tuple(o for o in env.objects if o.id != first.object))
    with pytest.raises(InputError, match=rf"plan.json: object {first.object} \(a particle near \(\d+, \d+\)\) is "
                                         r"gone: no particle within 1000 nm"):
        rv.adopt(layout, gone, 10.0, PlanOptions())
    (x0, y0), (x1, y1) = first.tip_path[0], first.expect.at
    mid = ((x0 + x1) / 2, (y0 + y1) / 2)
    crowded = replace(env, objects=(*env.objects, EnvObject("new", "particle", mid, 80.0)))
    with pytest.raises(InputError, match=rf"plan.json: a particle at \(\d+, \d+\), not in the plan, lies in the way "
                                         rf"of push {first.id} \({first.object}\); plan again"):
        rv.adopt(layout, crowded, 10.0, PlanOptions())
