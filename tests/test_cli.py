"""The command line: exit codes, one-line errors, nothing written on failure."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from nanoasm.cli import main
from nanoasm.examples import path as example
from nanoasm.world.scene import load_scene


def run(capsys, *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("nanoasm: error: ")
    assert "Traceback" not in err
    return lines[0]


def test_layout_check_bundled(capsys):
    code, out, err = run(capsys, "layout", "check", str(example("bowtie.toml")))
    assert code == 0 and "ok" in out and "6 particle slot(s), 1 rod slot(s)" in out and err == ""


def test_layout_check_bad_file(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text('format = "nanoasm.layout/1"\narea = [100, 100]\n[[target]]\nkind = "particle"\n'
                 'at = [50, 50]\ndiameter = -3\n')
    code, out, err = run(capsys, "layout", "check", str(p))
    assert code == 1 and out == ""
    assert one_error_line(err) == f"nanoasm: error: {p}: target[1].diameter: must be positive, got -3"


def test_layout_convert_round_trip_and_refusals(tmp_path, capsys):
    out_toml = tmp_path / "copy.toml"
    code, out, _ = run(capsys, "layout", "convert", str(example("bowtie.toml")), "-o", str(out_toml))
    assert code == 0 and out_toml.exists()
    code, _, err = run(capsys, "layout", "convert", str(out_toml), "-o", str(tmp_path / "x.svg"))
    assert code == 1 and "output must end in .toml or .json" in one_error_line(err)
    code, _, err = run(capsys, "layout", "convert", str(out_toml), "-o", str(tmp_path / "y.json"),
                       "--scale", "2")
    assert code == 1 and "apply only to SVG, GDSII and DXF" in one_error_line(err)
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "nanoasm.layout/1", "area": [1, 1], "target": [{"kind": "rod"')
    code, _, err = run(capsys, "layout", "convert", str(bad), "-o", str(tmp_path / "z.toml"))
    assert code == 1 and "truncated JSON" in one_error_line(err)
    assert not (tmp_path / "z.toml").exists() and not (tmp_path / "y.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json", "copy.toml"]


def test_scene_random_then_check(tmp_path, capsys):
    out_file = tmp_path / "s.toml"
    code, out, _ = run(capsys, "scene", "random", "--particles", "25", "--rods", "3", "--obstacles", "2",
                       "--seed", "4", "--drift", "0.3", "-0.1", "-o", str(out_file))
    assert code == 0
    scene = load_scene(out_file)
    assert len(scene.objects) == 28 and scene.seed == 4 and scene.drift.velocity == (0.3, -0.1)
    code, out, _ = run(capsys, "scene", "check", str(out_file))
    assert code == 0 and "25 particle(s), 3 rod(s), 2 obstacle(s)" in out


@pytest.mark.parametrize("args,fragment", [
    (["--particles", "-1"], "--particles: must not be negative"),
    (["--particles", "9000", "--area", "1000", "1000"], "--particles: only"),
    (["--particle-diameter", "50", "10"], "--particle-diameter: needs 0 < MIN <= MAX"),
    (["--seed", "-2"], "--seed: must not be negative"),
    (["--height-noise", "nan"], "--height-noise"),
    (["--height-noise", "-1"], "--height-noise: must not be negative"),
    (["--drift", "inf", "0"], "--drift: x must be finite"),
    (["--drift", "0.1", "0", "--random-walk", "-0.1"], "--random-walk: must not be negative"),
    (["--particles", "many"], "Invalid value for '--particles'"),
])
def test_scene_random_refusals(tmp_path, capsys, args, fragment):
    out_file = tmp_path / "s.toml"
    code, _, err = run(capsys, "scene", "random", *args, "-o", str(out_file))
    assert code in (1, 2) and fragment in one_error_line(err)
    assert not out_file.exists()


def test_usage_errors_are_one_line(capsys):
    code, _, err = run(capsys, "layout", "check")
    assert code == 2 and "Missing argument" in one_error_line(err)
    code, _, err = run(capsys, "layout", "check", "--nope", "x")
    assert code == 2 and "No such option" in one_error_line(err)
    code, _, err = run(capsys, "frobnicate")
    assert code == 2 and "No such command" in one_error_line(err)
    code, out, _ = run(capsys, "--version")
    assert code == 0 and out.startswith("nanoasm ")
    code, out, _ = run(capsys)
    assert code == 0 and "layout" in out


@pytest.mark.skipif(shutil.which("nanoasm") is None and not os.path.exists(
    os.path.join(os.path.dirname(sys.executable), "nanoasm")), reason="console script not installed")
def test_console_script(tmp_path):
    exe = shutil.which("nanoasm") or os.path.join(os.path.dirname(sys.executable), "nanoasm")
    ok = subprocess.run([exe, "layout", "check", str(example("bowtie.toml"))], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    (tmp_path / "e.toml").write_bytes(b"")
    bad = subprocess.run([exe, "scene", "check", str(tmp_path / "e.toml")], capture_output=True, text=True)
    assert bad.returncode == 1
    assert bad.stderr.strip() == f"nanoasm: error: {tmp_path / 'e.toml'}: file is empty"


def test_identify_a_simulated_scan(tmp_path, capsys):
    import numpy as np

    from nanoasm.bodies import Body
    from nanoasm.world.environment import load_environment
    from nanoasm.world.readers import save_height_image
    from nanoasm.world.render import make_surface, render_scan

    rng = np.random.default_rng(3)
    bodies = [Body("a", "particle", (1000.0, 1200.0), 80.0),
              Body("b", "rod", (3000.0, 2500.0), 60.0, 30.0, 600.0)]
    surface = make_surface(bodies, [], (5000.0, 5000.0), rng=rng)
    save_height_image(render_scan(surface, 10.0, rng=rng), tmp_path / "scan.npz")
    code, out, err = run(capsys, "identify", str(tmp_path / "scan.npz"), "-o", str(tmp_path / "env.json"))
    assert code == 0, err
    assert "1 particle(s), 1 rod(s)" in out
    env = load_environment(tmp_path / "env.json")
    p = next(o for o in env.objects if o.kind == "particle")
    assert abs(p.at[0] - 1000) < 2 and abs(p.at[1] - 1200) < 2 and abs(p.diameter - 80) < 4
    code, _, err = run(capsys, "identify", str(tmp_path / "nope.npz"), "-o", str(tmp_path / "e.json"))
    assert code == 1 and "no such file" in one_error_line(err)
    code, _, err = run(capsys, "identify", str(tmp_path / "scan.npz"), "-o", str(tmp_path / "e.json"),
                       "--cut", "-1")
    assert code == 1 and "--cut: must be positive" in one_error_line(err)
    assert not (tmp_path / "e.json").exists()


def test_run_without_the_ni_driver_says_so_in_one_line(capsys, tmp_path):
    pytest.importorskip("nidaqmx")
    code, _, err = run(capsys, "run", str(example("bowtie.toml")), "--instrument",
                       str(example("instrument_ni.toml")), "--report", str(tmp_path / "r.json"))
    assert code == 1 and "NI-DAQmx driver not found" in one_error_line(err)
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("strategy", ["open-loop", "local-scan", "anchor"])
def test_run_refuses_a_strategy_whose_report_could_not_tell_the_truth(capsys, tmp_path, strategy):
    code, _, err = run(capsys, "run", str(example("bowtie.toml")), "--instrument",
                       str(example("instrument_ni.toml")), "--strategy", strategy, "--report", str(tmp_path / "r.json"))
    assert code == 1 and f"--strategy: {strategy} measures no drift" in one_error_line(err)
    assert not (tmp_path / "r.json").exists()


def test_dry_run_refuses_bad_options(capsys, tmp_path):
    code, _, err = run(capsys, "dry-run", "--strategy", "psychic")
    assert code == 1 and "--strategy: unknown strategy" in one_error_line(err)
    code, _, err = run(capsys, "dry-run", str(example("bowtie_scene.toml")))
    assert code == 1 and "give both a scene and a layout" in one_error_line(err)
    code, _, err = run(capsys, "dry-run", "--report", str(tmp_path / "r.txt"))
    assert code == 1 and "report must end in .json" in one_error_line(err)
    for args, text in ((["--budget", "0"], "--budget: must be positive"),
                       (["--budget", "nan"], "--budget: must be finite"),
                       (["--seed", "-1"], "--seed: must not be negative"),
                       (["--planner", "psychic"], "--planner: unknown planner"),
                       (["--resume", "x.mcap", "--budget", "-2"], "--budget: must be positive")):
        code, _, err = run(capsys, "dry-run", *args)
        assert code == 1 and text in one_error_line(err)


def test_ctrl_c_stops_a_dry_run_with_exit_130_and_one_line(tmp_path):
    import signal
    import time

    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.Popen([sys.executable, "-m", "nanoasm.cli", "dry-run"], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            # a shell may start us with SIGINT ignored, which the child would inherit
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(4.0)                       # into the full scan or the plan
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "nanoasm: interrupted"


def test_outputs_are_written_with_the_usual_permissions(tmp_path):
    from nanoasm.fileio import write_atomic

    mask = os.umask(0o022)
    try:
        write_atomic(tmp_path / "a.txt", "x")
        write_atomic(tmp_path / "b.bin", b"x", mode=0o600)
    finally:
        os.umask(mask)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "b.bin").stat().st_mode & 0o777 == 0o600


@pytest.mark.parametrize("label", ["dry-run", "run"])
def test_the_progress_line_names_the_kind_of_run(monkeypatch, label):
    from rich.console import Console

    from nanoasm import cli, progress

    bars = []
    real = progress.progress_bar
    monkeypatch.setattr(progress, "progress_bar", lambda console: bars.append(real(console)) or bars[-1])
    monkeypatch.setattr(Console, "is_terminal", property(lambda self: True))
    shown: list[str] = []
    with cli._run_progress(label) as subscribers:
        task = bars[0].tasks[0]
        shown.append(task.description)
        for topic, doc in (("progress", {"step": "phase", "text": "full scan"}),
                           ("event", {"t": 1.0, "level": "info", "text": "push 1 of 6"}),
                           ("checkpoint", {"t": 2.0, "counts": {"pushes": 1}, "remaining": ["a", "b"]})):
            for follow in subscribers:
                follow(topic, doc)
            shown.append(f"{task.description}: {task.completed}/{task.total}")
    assert shown == [f"{label}: starting", f"{label}: full scan: 0/None", f"{label}: full scan - push 1 of 6: 0/None",
                     f"{label}: full scan - push 1 of 6: 1/3"]


@pytest.mark.parametrize("args,fragment", [
    (["--margin", "-1"], "--margin: must not be negative"),
    (["--tip-radius", "0"], "--tip-radius: must be positive"),
    (["--budget", "-inf"], "--budget: must be finite"),
    (["--seed", "-3"], "--seed: must not be negative"),
])
def test_plan_refuses_bad_numbers_before_reading_files(tmp_path, capsys, args, fragment):
    code, _, err = run(capsys, "plan", str(tmp_path / "none.toml"), "--env", str(tmp_path / "none.json"),
                       "-o", str(tmp_path / "p.json"), *args)
    assert code == 1 and fragment in one_error_line(err)
    assert not (tmp_path / "p.json").exists()
