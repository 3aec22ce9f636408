"""Issue 15, the rest: scene parameters at extremes are refused by ``scene check`` and
``dry-run`` alike (they were internal errors or hangs of the dry-run), ``[timing]
travel_speed`` is refused (nothing reads it), ``identify`` keeps every object of an image
with a non-zero origin inside the environment's area, and ``review`` of a log of many
slots lists 10 and counts the rest."""

from __future__ import annotations


import numpy as np
import pytest
from fuzzkit import TINY_LAYOUT, TINY_SCENE
from test_hostile_inputs import _particles

from nanoasm.cli import main
from nanoasm.examples import path as example
from nanoasm.instrument.protocol import MAX_SCANNER_SPEED, MIN_SCANNER_SPEED
from nanoasm.listing import LISTED
from nanoasm.world import limits
from nanoasm.world.environment import load_environment

SCENE, LAYOUT = TINY_SCENE, TINY_LAYOUT     # one slot, two particles, 1500 x 1500 nm

#: (table, key, value, what the one line says). Each was an internal error of the dry-run
#: (or, marked hang, a dry-run that never ended) while ``scene check`` passed it.
EXTREMES = [
    ("tip", "radius", "1e-300", f"must be at least {limits.MIN_TIP_RADIUS:g}"),
    ("tip", "radius", "1e308", f"must be at most {limits.MAX_SCENE_TIP_RADIUS:g}"),
    ("cantilever", "K_n", "1e308", f"must be at most {limits.MAX_LEVER_GAIN:g}"),
    ("cantilever", "K_n", "1e-300", f"must be at least {limits.MIN_LEVER_GAIN:g}"),
    ("cantilever", "length", "1e-300", f"must be at least {limits.MIN_LEVER_LENGTH:g}"),
    ("cantilever", "length", "1e308", f"must be at most {limits.MAX_LEVER_LENGTH:g}"),
    ("scanner", "max_speed", "1e-300", f"must be at least {MIN_SCANNER_SPEED:g}"),
    ("scanner", "max_speed", "1e308", f"must be at most {MAX_SCANNER_SPEED:g}"),
    ("timing", "full_scan_line", "1e308", f"must be at most {limits.MAX_SCAN_LINE_TIME:g}"),
    ("timing", "full_scan_line", "1e-300", f"must be at least {limits.MIN_SCAN_LINE_TIME:g}"),
    ("timing", "scan_line_sample", "1e308", f"must be at most {limits.MAX_SAMPLE_TIME:g}"),
    ("timing", "scan_line_sample", "1e-300", f"must be at least {limits.MIN_SAMPLE_TIME:g}"),
    ("timing", "scan_line_overhead", "1e308", f"must be at most {limits.MAX_PAUSE:g}"),
    ("timing", "mode_switch", "1e308", f"must be at most {limits.MAX_PAUSE:g}"),
    ("timing", "push_speed", "1e308", f"must be at most {MAX_SCANNER_SPEED:g}"),
    ("sim", "roughness_rms", "1e308", f"must be at most {limits.MAX_ROUGHNESS:g}"),
    ("sim", "roughness_length", "1e-300", f"must be at least {limits.MIN_ROUGHNESS_LENGTH:g}"),
    ("sim", "roughness_length", "1e308", f"must be at most {limits.MAX_ROUGHNESS_LENGTH:g}"),
    ("sim", "stop_time", "1e308", f"must be at most {limits.MAX_STOP_TIME:g}"),
    ("sim", "stop_time", "1e-300", f"must be at least {limits.MIN_STOP_TIME:g}"),
    ("vdw", "range", "1e308", f"must be at most {limits.MAX_VDW_RANGE:g}"),              # hang
    ("vdw", "amplitude", "1e308", f"must be at most {limits.MAX_VDW_AMPLITUDE:g}"),
    ("drift_change", "jump_every", "1e-9", f"must be 0 (one jump) or at least {limits.MIN_JUMP_EVERY:g} s"),  # hang
    ("drift_change", "jump_duration", "1e308", f"must be at most {limits.MAX_PAUSE:g}"),
    ("timing", "travel_speed", "3000", "has no effect: a lifted tip travels at the scanner's slew limit"),
]


def _files(tmp_path, table: str, key: str, value: str):
    scene, layout = tmp_path / "scene.toml", tmp_path / "layout.toml"
    scene.write_text(f"{SCENE}[{table}]\n{key} = {value}\n")
    layout.write_text(LAYOUT)
    return scene, layout


def _one_line(capsys, code: int, start: str) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 1 and len(lines) == 1, captured.err
    assert lines[0].startswith(start), lines[0]
    assert "internal error" not in lines[0]
    return lines[0]


@pytest.mark.parametrize("table, key, value, says", EXTREMES,
                         ids=[f"{t}.{k}={v}" for t, k, v, _ in EXTREMES])
def test_scene_check_and_dry_run_refuse_an_extreme(tmp_path, capsys, table, key, value, says):
    scene, layout = _files(tmp_path, table, key, value)
    line = _one_line(capsys, main(["scene", "check", str(scene)]), f"nanoasm: error: {scene}: {table}.{key}: ")
    assert says in line
    report = tmp_path / "report.json"
    code = main(["dry-run", str(scene), str(layout), "--report", str(report), "--log", str(tmp_path / "run.mcap")])
    assert _one_line(capsys, code, f"nanoasm: error: {scene}: {table}.{key}: ") == line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["layout.toml", "scene.toml"]


def test_roughness_grid_is_bounded_by_the_area(tmp_path, capsys):
    """A correlation length within its limits is still refused where its grid over the
    scene's area would exceed MAX_PIXELS nodes."""
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE.replace("[1500, 1500]", "[40000, 40000]") + "[sim]\nroughness_length = 2\n")
    line = _one_line(capsys, main(["scene", "check", str(scene)]),
                     f"nanoasm: error: {scene}: sim.roughness_length: must be at least ")
    assert "MAX_PIXELS" in line
    scene.write_text(SCENE.replace("[1500, 1500]", "[40000, 40000]") + "[sim]\nroughness_length = 2\n"
                     "roughness_rms = 0\n")
    assert main(["scene", "check", str(scene)]) == 0           # no roughness, no grid


def test_overlapping_drift_jumps_are_bounded(tmp_path, capsys):
    scene, _ = _files(tmp_path, "drift_change", "jump_every", "1.0")
    scene.write_text(scene.read_text() + "jump_duration = 100.0\n")
    line = _one_line(capsys, main(["scene", "check", str(scene)]),
                     f"nanoasm: error: {scene}: drift_change.jump_duration: ")
    assert f"at most {limits.MAX_OVERLAPPING_JUMPS} x jump_every" in line


@pytest.mark.parametrize("table, key, value", [
    ("tip", "radius", limits.MIN_TIP_RADIUS), ("cantilever", "K_n", limits.MAX_LEVER_GAIN),
    ("scanner", "max_speed", MAX_SCANNER_SPEED), ("timing", "full_scan_line", limits.MIN_SCAN_LINE_TIME),
    ("sim", "roughness_length", limits.MIN_ROUGHNESS_LENGTH), ("vdw", "range", limits.MAX_VDW_RANGE),
    ("drift_change", "jump_every", limits.MIN_JUMP_EVERY), ("drift_change", "jump_every", 0),
])
def test_values_at_the_limits_are_accepted(tmp_path, capsys, table, key, value):
    scene, _ = _files(tmp_path, table, key, repr(value))
    assert main(["scene", "check", str(scene)]) == 0, capsys.readouterr().err


def test_a_dry_run_at_the_limits_ends_normally(tmp_path, capsys):
    """The extreme values together still make a dry-run that ends (no internal error)."""
    scene, layout = _files(tmp_path, "tip", "radius", repr(limits.MIN_TIP_RADIUS))
    scene.write_text(scene.read_text() + f"[sim]\nroughness_length = {limits.MIN_ROUGHNESS_LENGTH!r}\n"
                     f"stop_time = {limits.MIN_STOP_TIME!r}\n[vdw]\nrange = {limits.MAX_VDW_RANGE!r}\n"
                     f"[drift_change]\njump = 50.0\njump_at = 60.0\njump_every = {limits.MIN_JUMP_EVERY!r}\n")
    assert main(["dry-run", str(scene), str(layout)]) == 0, capsys.readouterr().err


# -- identify: an image whose origin is not (0, 0) ---------------------------------------------

def test_identify_keeps_objects_of_an_offset_image_inside_its_area(tmp_path, capsys):
    z = _particles()                                # at pixels (30, 30), (90, 40), (60, 100)
    scan, out = tmp_path / "offset.npz", tmp_path / "env.json"
    np.savez(scan, height=z, pixel_size=np.float64(10.0), origin=np.array([25000.0, -7000.0]))
    assert main(["identify", str(scan), "-o", str(out)]) == 0, capsys.readouterr().err
    env = load_environment(out)                 # refuses objects outside the area
    assert env.area == (1280.0, 1280.0) and len(env.objects) == 3
    found = sorted((o.at[0] / 10 - 0.5, o.at[1] / 10 - 0.5) for o in env.objects)    # pixels
    assert np.allclose(found, [(30, 30), (60, 100), (90, 40)], atol=1.0), found


# -- review of a log of many slots -------------------------------------------------------------

def test_review_lists_10_slots_and_counts_the_rest(tmp_path, capsys, monkeypatch):
    from nanoasm import review as review_mod
    from nanoasm.cad.layout import load_layout

    layout = load_layout(example("bowtie.toml"))
    slots = [review_mod.SlotRow(f"s{i}", f"o{i}", 3.0, i % 3 != 0) for i in range(1, 501)]
    rev = review_mod.Review("big.mcap", True, None, "dry-run", {}, 10.0, layout=layout, slots=slots,
                            unfilled=[(f"u{i}", "no object left") for i in range(1, 301)])
    monkeypatch.setattr(review_mod, "review", lambda path: rev)
    log = tmp_path / "big.mcap"
    log.write_bytes(b"")
    assert main(["review", str(log)]) == 0
    out = capsys.readouterr().out
    shown = [line for line in out.splitlines() if "slot s" in line]
    assert len(shown) == LISTED
    assert "and 490 more slot(s): 327 filled, 163 missed" in out
    assert sum("unfilled u" in line for line in out.splitlines()) == LISTED
    assert "and 290 more unfilled" in out
    assert len(out.splitlines()) < 60
