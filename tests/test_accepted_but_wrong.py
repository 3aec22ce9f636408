"""Files the checks passed and the run then crashed on or said nothing useful about
(issue 15, "accepted but wrong"): each is now refused by the check, in one line naming
the file, the key and the problem, exit 1, no traceback, under 10 s, or the run says why.

Every file is generated here, small. One that could blow memory or hang on the code
before runs in a subprocess under a 1 GiB limit and a timeout.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, DataEnd, Footer, Header, Message, Schema
from test_hostile_inputs import MCAP_MAGIC, _cli, _particles, _refused, _run

from nanoasm.cad.layout import MAX_TARGETS
from nanoasm.cli import main
from nanoasm.errors import InputError
from nanoasm.executor.instrument_file import load_instrument_config
from nanoasm.executor.strategy import ExecOptions
from nanoasm.examples import path as example
from nanoasm.param import ParamError
from nanoasm.world.limits import MAX_LAYOUT_SIDE, MAX_PIXELS


def _particles_toml(table: str, *slots: tuple[float, float, float]) -> str:
    """``[[table]]`` blocks of particles, one per ``(x, y, diameter)``."""
    return "".join(f'\n[[{table}]]\nkind = "particle"\nat = [{x}, {y}]\ndiameter = {d}\n' for x, y, d in slots)


SCENE = ('format = "nanoasm.scene/1"\narea = [3000, 3000]\nseed = 1\n'
         + _particles_toml("object", (800, 800, 90), (2200, 2200, 90), (800, 2200, 90)))


def _scene(tmp_path: Path, extra: str = "", name: str = "scene.toml", area: str = "3000, 3000") -> Path:
    path = tmp_path / name
    path.write_text(SCENE.replace("3000, 3000", area) + "\n" + extra)
    return path


def _layout(tmp_path: Path, area: str = "3000, 3000") -> Path:
    path = tmp_path / "layout.toml"
    path.write_text(f'format = "nanoasm.layout/1"\narea = [{area}]\n'
                    + _particles_toml("target", (1400, 1500, 90), (1600, 1500, 90)))
    return path


def _out(capsys, *args: str | Path) -> tuple[int, str, str]:
    """``nanoasm ARGS`` in this process: (exit code, stdout, stderr)."""
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def _text(out: str) -> str:
    """A rich table's text as one line of words: borders dropped, wrapped cells joined."""
    return " ".join(re.sub(r"[│┃┌┐└┘─━┬┴┼├┤]", " ", out).split())


def _grid_layout(path: Path, n: int, diameter: float = 50.0, pitch: float = 128.0) -> Path:
    """A layout of ``n`` particle slots on a square grid."""
    side = math.ceil(math.sqrt(n))
    targets = [{"kind": "particle", "at": [100 + pitch * (i % side), 100 + pitch * (i // side)],
                "diameter": diameter} for i in range(n)]
    extent = 200 + pitch * side
    path.write_text(json.dumps({"format": "nanoasm.layout/1", "area": [extent, extent], "target": targets}))
    return path


# -- scenes: what scene check passed and dry-run crashed on --------------------------------------

CRASHING_SCENES = {
    "drift 1e308": ("[drift]\nvelocity = [1e308, 0]\nrandom_walk = 0.1\n", "drift.velocity", "at most 10"),
    "sample rate 1e9 (7.5 GB)": ("[scanner]\nsample_rate = 1e9\n", "scanner.sample_rate", "at most 100000"),
    "random walk 1e308": ("[drift]\nvelocity = [0.1, 0]\nrandom_walk = 1e308\n", "drift.random_walk",
                          "at most 10"),
    "drift acceleration 1e300": ("[drift_change]\nacceleration = [1e300, 0]\n", "drift_change.acceleration",
                                 "at most 0.01"),
    "scanner range 1e308": ("[scanner]\nxy_range = [1e308, 1e308]\n", "scanner.xy_range", "at most 1e+06"),
}


@pytest.mark.parametrize("case", list(CRASHING_SCENES))
def test_a_scene_the_dry_run_crashed_on_is_refused_by_scene_check(tmp_path, capsys, case):
    extra, key, words = CRASHING_SCENES[case]
    scene, report = _scene(tmp_path, extra), tmp_path / "r.json"
    _refused(_cli(capsys, "scene", "check", scene), scene, key, words)
    _refused(_run("dry-run", scene, _layout(tmp_path), "--report", report, cwd=tmp_path), scene, key, words)
    assert not report.exists()


def test_a_scene_beyond_the_scanner_is_refused_by_scene_check(tmp_path, capsys):
    scene = _scene(tmp_path, area="1e9, 1e9")
    for args in (("scene", "check", scene), ("dry-run", scene, _layout(tmp_path))):
        _refused(_cli(capsys, *args), scene, "area", "exceeds the scanner's XY range 90000 x 90000 nm")


@pytest.mark.parametrize("extra, key, words", [
    ("[drift]\nvelocity = [1e6, 0]\nrandom_walk = 0.1\n", "drift.velocity", "at most 10, got 1000000.0"),
    ("[noise]\nheight_rms = 1e300\n", "noise.height_rms", "at most 10, got 1e+300"),
    ("[drift_change]\njump = 1e308\njump_at = 10\n", "drift_change.jump", "at most 10000"),
])
def test_a_scene_that_could_fill_nothing_is_refused(tmp_path, capsys, extra, key, words):
    """Drift of 1e6 nm/s and noise of 1e300 nm passed and gave '0 of 2 filled, RMS nan nm'."""
    scene = _scene(tmp_path, extra)
    for args in (("scene", "check", scene), ("dry-run", scene, _layout(tmp_path))):
        _refused(_cli(capsys, *args), scene, key, words)


def test_a_dry_run_that_fills_nothing_says_why_and_prints_no_nan(tmp_path, capsys):
    """3 nm/s is plausible drift, but it smears the full scan's particles into obstacles."""
    scene = _scene(tmp_path, "[drift]\nvelocity = [3, 0]\nrandom_walk = 0.1\n")
    assert _cli(capsys, "scene", "check", scene)[0] == 0
    code, out, _ = _out(capsys, "dry-run", scene, _layout(tmp_path))
    text = _text(out)
    assert code == 0
    assert not re.search(r"\bnan\b", text) and "no assigned slot filled: no error to measure" in text, text
    assert "identified 0 particle(s), 0 rod(s), 0 wire(s)" in text, text


# -- layouts ------------------------------------------------------------------------------------

def test_a_layout_area_of_1e308_is_refused_by_layout_check(tmp_path, capsys):
    layout = _layout(tmp_path, area="1e308, 1e308")
    _refused(_cli(capsys, "layout", "check", layout), layout, "area", "at most 40960 nm", "MAX_LAYOUT_SIDE")
    _refused(_run("dry-run", _scene(tmp_path), layout, cwd=tmp_path), layout, "area", "MAX_LAYOUT_SIDE")


def test_a_layout_of_100k_targets_is_refused_before_they_are_read(tmp_path, capsys):
    """100 000 targets within MAX_LAYOUT_SIDE: the dry-run ran out of memory after 52 s."""
    layout = _grid_layout(tmp_path / "many.json", 100_000)
    assert json.loads(layout.read_text())["area"][0] <= MAX_LAYOUT_SIDE
    words = ("target", f"100000 targets; a layout may have at most {MAX_TARGETS} (MAX_TARGETS)")
    _refused(_cli(capsys, "layout", "check", layout), layout, *words)
    _refused(_run("dry-run", _scene(tmp_path), layout, cwd=tmp_path), layout, *words)


def test_the_layout_side_limit_is_the_full_scan_the_run_makes():
    assert MAX_LAYOUT_SIDE == ExecOptions().pixel_size * math.isqrt(MAX_PIXELS)


def test_a_layout_larger_than_the_scenes_scanner_is_refused_before_the_run(tmp_path, capsys):
    scene = _scene(tmp_path, "[scanner]\nxy_range = [4000, 4000]\nnm_per_volt = [200, 200, 250]\n")
    layout, report = _layout(tmp_path, area="5000, 4000"), tmp_path / "r.json"
    _refused(_cli(capsys, "dry-run", scene, layout, "--report", report), layout, "area",
             "a full scan of 5000 x 5000 nm does not fit the scanner's XY range 4000 x 4000 nm")
    assert not report.exists()


def test_plan_lists_ten_unfilled_slots_and_counts_the_rest(tmp_path, capsys):
    layout = _grid_layout(tmp_path / "grid.json", MAX_TARGETS)
    env = tmp_path / "env.json"
    area = json.loads(layout.read_text())["area"]       # a scan of the whole layout (issue 17: else refused)
    env.write_text(json.dumps({"format": "nanoasm.env/1", "area": area, "objects": [
        {"id": f"o{i}", "kind": "particle", "at": [300 + 200 * i, 500], "diameter": 50} for i in range(4)]}))
    out = tmp_path / "plan.json"
    code, stdout, err = _out(capsys, "plan", layout, "--env", env, "-o", out)
    lines = stdout.splitlines()
    assert code == 0 and err == ""
    assert len(lines) <= 14 and sum(line.startswith("  unfilled ") for line in lines) == 10
    assert lines[-1] == f"  … and {MAX_TARGETS - 4 - 10} more unfilled (see {out})"
    assert len(json.loads(out.read_text())["unfilled"]) == MAX_TARGETS - 4


def test_a_dry_run_summary_lists_ten_slots_not_filled(tmp_path, capsys):
    scene = _scene(tmp_path)
    layout = _grid_layout(tmp_path / "grid.json", 15, diameter=40.0, pitch=150.0)
    code, out, _ = _out(capsys, "dry-run", scene, layout)
    assert code == 0 and "and 5 more not filled (the report lists every slot)" in _text(out)
    assert sum("unfilled t" in row for row in out.splitlines()) == 10


# -- push speed -------------------------------------------------------------------------------

def test_a_push_speed_of_1e_9_is_refused(tmp_path, capsys):
    scene = _scene(tmp_path, "[timing]\npush_speed = 1e-9\n")
    _refused(_cli(capsys, "scene", "check", scene), scene, "timing.push_speed", "at least 1, got 1e-09")
    with pytest.raises(ParamError, match="push_speed: must be at least 1"):
        ExecOptions(push_speed=1e-9)


def test_an_instrument_files_timing_table_is_refused_as_such(tmp_path, capsys):
    inst = tmp_path / "lab.toml"
    inst.write_text(example("instrument_ni.toml").read_text() + "\n[timing]\npush_speed = 1e-9\n")
    with pytest.raises(InputError) as e:
        load_instrument_config(inst)
    assert str(e.value).startswith(f"{inst}: timing: not an instrument file table")
    assert "pushes at 200 nm/s" in str(e.value) and "did you mean" not in str(e.value)


def test_a_scenes_push_speed_is_the_dry_runs(tmp_path, capsys):
    """It was silently ignored: the dry-run pushed at 200 nm/s whatever the scene said."""
    times = {}
    for speed in (200, 50):
        report = tmp_path / f"r{speed}.json"
        scene = _scene(tmp_path, f"[timing]\npush_speed = {speed}\n", name=f"s{speed}.toml")
        assert _cli(capsys, "dry-run", scene, _layout(tmp_path), "--report", report)[0] == 0
        times[speed] = json.loads(report.read_text())["instrument_time"]["push"]
    capsys.readouterr()
    assert times[50] > 2.5 * times[200] > 0


# -- environments -----------------------------------------------------------------------------

ENV = {"format": "nanoasm.env/1", "area": [3000, 3000],
       "objects": [{"id": "o1", "kind": "particle", "at": [500, 500], "diameter": 90}]}


@pytest.mark.parametrize("change, key, words", [
    ({"objects": [{"id": "o1", "kind": "particle", "at": [1e308, 1e308], "diameter": 90}]},
     "objects[1].at", "lies outside the area 3000 x 3000"),
    ({"objects": [{"id": "o1", "kind": "particle", "at": [500, 500], "diameter": 90},
                  {"id": "o2", "kind": "particle", "at": [3500, 100], "diameter": 90}]},
     "objects[2].at", "object 'o2' at (3500, 100) lies outside"),
    ({"objects": [{"id": "o1", "kind": "particle", "at": [500, 500], "diameter": 1e308}]},
     "objects[1].diameter", "more than the area measures across"),
    ({"area": [1e308, 1e308]}, "area", "MAX_SCANNER_RANGE"),
    ({"obstacles": [{"polygon": [[0, 0], [100, 0], [100, 1e308]], "height": 30}]},
     "obstacles[1].polygon[3]", "lies outside the area"),
    ({"obstacles": [{"polygon": [[0, 0], [100, 0], [100, 100]], "height": 1e308}]},
     "obstacles[1].height", "at most 1e+06 nm"),
])
def test_an_environment_beyond_its_area_is_refused(tmp_path, capsys, change, key, words):
    env, out = tmp_path / "env.json", tmp_path / "plan.json"
    env.write_text(json.dumps({**ENV, **change}))
    _refused(_cli(capsys, "plan", _layout(tmp_path), "--env", env, "-o", out), env, key, words)
    assert not out.exists()


def test_an_object_cut_by_the_border_may_have_its_centre_beyond_it(tmp_path, capsys):
    """As identification finds one: a particle cut by the right border, centre 20 nm beyond."""
    env, out = tmp_path / "env.json", tmp_path / "plan.json"
    env.write_text(json.dumps({**ENV, "objects": [
        *ENV["objects"], {"id": "o2", "kind": "particle", "at": [3020, 100], "diameter": 90, "edge": True}]}))
    assert _cli(capsys, "plan", _layout(tmp_path), "--env", env, "-o", out)[0] == 0
    assert out.exists()


# -- scans with half their heights missing ------------------------------------------------------

def test_exactly_half_the_pixels_nan_in_a_block_warns(tmp_path, capsys):
    z = _particles()
    z[: z.shape[0] // 2] = np.nan
    scan = tmp_path / "half.npy"
    np.save(scan, z)
    code, err, _ = _cli(capsys, "identify", scan, "-o", tmp_path / "o.json", "--pixel-size", "10")
    lines = err.strip().splitlines()
    assert code == 0 and len(lines) == 1 and lines[0].startswith(f"nanoasm: warning: {scan}: ")
    assert "(50%) have no finite height" in lines[0]


def test_one_pixel_beyond_half_is_refused_with_the_counts(tmp_path, capsys):
    """It said '50% of the pixels have no finite height; at most 50% may'."""
    z = _particles()
    n = z.size
    z.flat[: n // 2 + 1] = np.nan
    scan = tmp_path / "over.npy"
    np.save(scan, z)
    _refused(_cli(capsys, "identify", scan, "-o", tmp_path / "o.json", "--pixel-size", "10"), scan,
             f"{n // 2 + 1} of {n} pixels (50%)", f"at most 50% ({n // 2}) may")


# -- review of files that are no run log -------------------------------------------------------

def _junk_log(path: Path) -> Path:
    """An MCAP file of junk schemas and a /stop message, and no nanoasm start record."""
    rb = RecordBuilder()
    Header(profile="junk", library="junk").write(rb)
    Schema(id=1, name="nanoasm.Stop", encoding="jsonschema", data=os.urandom(30)).write(rb)
    Channel(id=1, schema_id=1, topic="/stop", message_encoding="json", metadata={}).write(rb)
    Message(channel_id=1, sequence=0, log_time=10**9, publish_time=10**9, data=b'{"state": null}').write(rb)
    DataEnd(data_section_crc=0).write(rb)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
    path.write_bytes(MCAP_MAGIC + rb.end())          # no closing magic: cut before its end
    return path


@pytest.mark.parametrize("make", ["random", "junk"])
def test_review_of_no_run_log_is_one_line(tmp_path, capsys, make):
    """Both gave exit 0 and a plot ('0 of 0 slot(s)', 'stopped None: None')."""
    path, plot = tmp_path / f"{make}.mcap", tmp_path / "p.png"
    if make == "random":
        path.write_bytes(MCAP_MAGIC + np.random.default_rng(15).bytes(4096))
    else:
        _junk_log(path)
    code, out, err = _out(capsys, "review", path, "--plot", plot)
    _refused((code, err, 0.0), path, "not a readable nanoasm run log", "no 'nanoasm' metadata record")
    assert out == "" and not plot.exists()
