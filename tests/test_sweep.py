"""Sweeps: cases, rows, the same table in this process, in worker processes and on Dask;
the ``nanoasm sweep`` command, its one-line errors and a clean Ctrl-C."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from nanoasm import sweep as sw
from nanoasm.cli import main

TINY = sw.grid(["tiny"], [1, 2], ["open-loop", "full"], knobs={"line_factor": [0.5]})


def without_wall(rows):
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]


@pytest.fixture(scope="module")
def serial_rows():
    return sw.sweep(TINY, workers=1)


def test_a_row_holds_the_case_its_figures_and_the_bound(serial_rows):
    assert len(serial_rows) == 8 and [r["case"] for r in serial_rows] == [c.label for c in TINY]
    for r in serial_rows:
        assert set(r) == set(sw.COLUMNS) and r["error"] is None
        assert r["slots"] == 2 and 0 <= r["fill_rate"] <= 1 and r["fill_rate"] == r["filled"] / 2
        assert r["bound_s"] > 0
        if r["strategy"] != "open-loop":     # the bound counts local scans, which open-loop skips
            # no run beats the physical bound, even without its full scan
            assert r["instrument_s"] - r["full_scan_s"] >= r["bound_switch_s"] > r["bound_s"]
            assert r["ratio_after_scan_switch"] == pytest.approx(
                (r["instrument_s"] - r["full_scan_s"]) / r["bound_switch_s"], rel=1e-3)
        assert r["ratio"] == pytest.approx(r["instrument_s"] / r["bound_s"], rel=1e-3)
        if r["filled"]:
            assert r["per_filled_slot_s"] == pytest.approx(r["instrument_s"] / r["filled"], abs=1e-3)
            assert 0 <= r["rms_error_nm"] <= 20        # filled: within the layout's tolerance
            assert r["rms_assigned_nm"] >= r["rms_error_nm"] - 1e-3   # misses only add to it
        else:
            assert r["per_filled_slot_s"] is None and r["rms_error_nm"] is None
    full = [r for r in serial_rows if r["strategy"] == "full"]
    assert all(r["local_scans"] > 0 for r in full)
    # open-loop scans nothing but the final check of every slot
    assert all(r["local_scans"] == r["slots"] for r in serial_rows if r["strategy"] == "open-loop")


def test_worker_processes_give_the_same_table(serial_rows):
    seen = []
    rows = sw.sweep(TINY, workers=2, progress=lambda done, total: seen.append((done, total)))
    assert without_wall(rows) == without_wall(serial_rows)
    assert seen[-1] == (8, 8) and [d for d, _ in seen] == sorted(d for d, _ in seen)


def test_a_dask_cluster_gives_the_same_table(serial_rows):
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None, processes=True) as cluster:
        rows = sw.sweep(TINY, scheduler=cluster.scheduler_address)
    assert without_wall(rows) == without_wall(serial_rows)


def test_the_scale_benchmark_runs_on_a_two_worker_dask_cluster_as_in_series():
    """bench/bench_scale.py's dry-runs (the scaleN family) on a distributed.LocalCluster of
    two worker processes, as README's recipe runs them: the same rows as in series."""
    from distributed import LocalCluster

    cases = sw.grid(sw.parse_families("scale10,scale20"), [1, 2], ["full"])
    serial = sw.sweep(cases, workers=1)
    assert all(r["error"] is None and r["slots"] in (3, 6) and r["pushes"] > 0 for r in serial)
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None, processes=True) as cluster:
        rows = sw.sweep(cases, scheduler=cluster.scheduler_address)
    assert without_wall(rows) == without_wall(serial)


def test_an_unreachable_scheduler_is_one_input_error():
    with pytest.raises(sw.InputError, match="--scheduler: cannot reach tcp://127.0.0.1:9"):
        sw.sweep(TINY[:1], scheduler="tcp://127.0.0.1:9")


def test_a_failing_case_is_a_row_and_the_sweep_goes_on(monkeypatch):
    import nanoasm.world.families as fam

    real = fam.family_case

    def flaky(name, seed, drift=0.3):
        if seed == 2:
            raise ValueError("boom")
        return real(name, seed, drift)

    monkeypatch.setattr(fam, "family_case", flaky)
    rows = sw.sweep(sw.grid(["tiny"], [1, 2], ["full"]), workers=1)
    assert rows[0]["error"] is None and rows[0]["filled"] is not None
    assert rows[1]["error"] == "ValueError: boom" and rows[1]["filled"] is None
    assert sw.medians(rows)[0]["errors"] == 1 and sw.medians(rows)[0]["runs"] == 2


def test_ctrl_c_keeps_the_finished_rows():
    def stop_after_two(done, total):
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(sw.Interrupted) as info:
        sw.sweep(TINY, workers=1, progress=stop_after_two)
    assert info.value.total == 8 and [r["case"] for r in info.value.rows] == [c.label for c in TINY[:2]]


def test_grid_varies_one_knob_at_a_time():
    cases = sw.grid(["tiny", "sparse"], [1, 2, 3], ["full", "kalman"], drifts=[0.05, 1.0],
                    knobs={"line_factor": [0.5, 2.0], "budget": [0.2]})
    assert len(cases) == 2 * 2 * (1 + 3) * 2 * 3
    assert {c.knob for c in cases} == {"default", "line_factor=0.5", "line_factor=2", "budget=0.2"}
    ex, plan = sw.Case("tiny", 1, "kalman", knobs=(("drift_q", 1e-4), ("budget", 0.2))).options()
    assert (ex.strategy.value, ex.drift_q, plan.budget, plan.seed) == ("kalman", 1e-4, 0.2, 1)


@pytest.mark.parametrize("kwargs, match", [
    (dict(family="huge", seed=1), "unknown scene family 'huge'"),
    (dict(family="tiny", seed=1, strategy="fast"), "unknown strategy 'fast'"),
    (dict(family="tiny", seed=-1), "seed must not be negative"),
    (dict(family="tiny", seed=1, knobs=(("speed", 1.0),)), "unknown knob 'speed'; one of pixel_size"),
    (dict(family="tiny", seed=1, knobs=(("line_factor", 1.0), ("line_factor", 2.0))), "given twice"),
    (dict(family="tiny", seed=1, knobs=(("line_factor", -1.0),)), "line_factor: must be positive"),
])
def test_bad_cases_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sw.Case(**kwargs)


def test_parsers():
    assert sw.parse_seeds("1-3,7,2") == [1, 2, 3, 7]
    assert sw.parse_names("all", ("a", "b"), "x") == ["a", "b"]
    assert sw.parse_knob("max_corrections=0,3") == ("max_corrections", [0, 3])
    assert sw.parse_knob("planner=rrt,prm") == ("planner", ["rrt", "prm"])
    assert sw.parse_numbers("0.05,1", "drift") == [0.05, 1.0]
    for fn, arg in ((sw.parse_seeds, "3-1"), (sw.parse_seeds, "a"), (sw.parse_knob, "line_factor"),
                    (sw.parse_knob, "line_factor=x"), (sw.parse_knob, "r_max=inf")):
        with pytest.raises(ValueError):
            fn(arg)
    with pytest.raises(ValueError):
        sw.parse_numbers("1,-2", "drift")


def test_tables_round_trip_with_empty_cells_for_missing_values(serial_rows, tmp_path):
    sw.write_table(serial_rows, tmp_path / "t.json")
    assert json.loads((tmp_path / "t.json").read_text()) == serial_rows
    sw.write_table(serial_rows, tmp_path / "t.csv")
    back = list(csv.DictReader((tmp_path / "t.csv").open()))
    assert [r["case"] for r in back] == [r["case"] for r in serial_rows]
    assert all((b["rms_error_nm"] == "") == (r["rms_error_nm"] is None) for b, r in zip(back, serial_rows))
    with pytest.raises(sw.InputError, match="must end in .csv or .json"):
        sw.write_table(serial_rows, tmp_path / "t.txt")


def test_medians_are_over_seeds(serial_rows):
    groups = sw.medians(serial_rows)
    assert len(groups) == 4 and all(g["runs"] == 2 and g["errors"] == 0 for g in groups)
    g = next(g for g in groups if g["strategy"] == "full" and g["knob"] == "default")
    full = [r for r in serial_rows if r["strategy"] == "full" and r["knob"] == "default"]
    assert g["instrument_s"] == pytest.approx(sum(r["instrument_s"] for r in full) / 2)


# -- the command ------------------------------------------------------------------------

def test_sweep_command_writes_the_table(tmp_path, capsys):
    out = tmp_path / "t.csv"
    code = main(["sweep", "--families", "tiny", "--seeds", "1", "--strategies", "full,open-loop",
                 "--workers", "1", "-o", str(out)])
    stdout, err = capsys.readouterr()
    assert code == 0 and err == ""
    assert "medians over seeds" in stdout and f"{out}: written: 2 row(s), 0 failed" in stdout
    rows = list(csv.DictReader(out.open()))
    assert [r["strategy"] for r in rows] == ["full", "open-loop"]


@pytest.mark.parametrize("args, option", [
    (["--families", "tiny,huge"], "--families"), (["--strategies", "fast"], "--strategies"),
    (["--seeds", "x"], "--seeds"), (["--knob", "speed=1"], "--knob"), (["--knob", "line_factor=-2"], "--knob"),
    (["--drift", "-1"], "--drift"), (["--workers", "0"], "--workers"), (["-o", "t.txt"], "-o"),
])
def test_bad_options_are_one_line_and_exit_2(args, option, tmp_path, capsys):
    code = main(["sweep", *args])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2 and out == "" and len(lines) == 1, err
    assert lines[0].startswith(f"nanoasm: error: Invalid value for '{option}'")
    assert not (tmp_path / "t.txt").exists()


def _processes_with(marker: str) -> list[int]:
    pids = []
    for env in Path("/proc").glob("[0-9]*/environ"):
        try:
            if marker.encode() in env.read_bytes():
                pids.append(int(env.parent.name))
        except OSError:
            continue
    return pids


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc")
def test_ctrl_c_stops_the_workers_and_keeps_the_finished_rows(tmp_path):
    marker = f"NANOASM_SWEEP_TEST={uuid.uuid4().hex}"
    env = {**os.environ, marker.split("=")[0]: marker.split("=")[1]}
    out = tmp_path / "t.csv"
    cmd = [sys.executable, "-m", "nanoasm.cli", "sweep", "--families", "sparse", "--seeds", "1-200",
           "--workers", "2", "-o", str(out)]
    # a shell may start us with SIGINT ignored, which the child would inherit
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(_processes_with(marker)) < 3:   # parent + 2 workers
        time.sleep(0.2)
    time.sleep(3.0)
    proc.send_signal(signal.SIGINT)
    stdout, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nanoasm: error: interrupted after "), err
    time.sleep(0.5)
    assert _processes_with(marker) == []
    if out.exists():
        done = int(lines[0].split("after ")[1].split(" of")[0])
        assert len(list(csv.DictReader(out.open()))) == done > 0
        assert f"rows written to {out}" in lines[0]
