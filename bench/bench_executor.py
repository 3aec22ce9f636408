"""Executor speed: overhead per push, DAC rate, instrument time against the physical bound.

Dry-runs (``nanoasm.dryrun.dry_run``, full strategy) of the bundled example
(``examples/bowtie_scene.toml`` + ``examples/bowtie.toml``) and of generated particle
scenes (``world/random_scene.py``, as ``nanoasm scene random``) with a small grid layout,
a few seeds each, all in one run:

- **executor overhead per push**: the run's execute wall time (``Outcome.summary.wall``:
  the procedure's wall time less identification and planning) less the wall time spent
  inside the instrument's methods, divided by the pushes. The instrument is measured by
  a timing proxy around the ``SimulatedAFM`` that implements the same ``Instrument``
  protocol (``dry_run`` is given it by replacing the ``SimulatedAFM`` name in
  ``nanoasm.dryrun`` for the duration of the run). Correction pushes are planned inside
  the execute phase (``nanoasm.executor.course.correction``); that planning is timed too and shown on
  its own. Target <= 10 ms per push.
- **where the overhead goes**: one more run under cProfile, paused whenever the
  instrument, identification or planning runs, so only the executor's own time remains;
  the top entries by own time and by cumulative time.
- **DAC sample generation** against real time at 100 kS/s: ``bench/bench_dac.py``'s own
  workload and timing (chunk 4096), called from here. Target >= 20x.
- **instrument time against the physical bound** (``executor/bound.py``) of the run's
  first plan: instrument time less the full scan, over the bound; and per filled slot
  (instrument time less the full scan per filled slot, over the bound per slot the plan
  assigned).

    python bench/bench_executor.py          # writes bench/RESULTS_executor.md
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import datetime
import io
import os
import platform
import pstats
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

import nanoasm.dryrun as dryrun
import nanoasm.executor.assembly as assembly
import nanoasm.planner as planner
from nanoasm.cad.layout import Layout, Target, load_layout
from nanoasm.dryrun import dry_run
from nanoasm.executor.bound import physical_bound
from nanoasm.executor.dac_frames import LinearDrift
from nanoasm.executor.strategy import ExecOptions
from nanoasm.instrument import Instrument, InstrumentConfig
from nanoasm.planner.replan import Replanner
from nanoasm.world.random_scene import SceneSpec, random_scene
from nanoasm.world.scene import load_scene
from nanoasm.world.sim import InstrumentClock, SimulatedAFM

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
import bench_dac  # noqa: E402  (bench/bench_dac.py: its workload and timing)

OVERHEAD_TARGET = 0.010       # s per push
DAC_TARGET = bench_dac.TARGET
PROTOCOL = ("clock", "write", "full_scan", "scan_line", "signals", "position", "park")


class Stopwatch:
    """Wall time per label of the work that is not the executor's; pauses ``profiler``
    (if any) meanwhile, so a profile holds the executor's own time only."""

    def __init__(self, profiler: cProfile.Profile | None = None, clock=time.perf_counter):
        self.profiler = profiler
        self.clock = clock          # time.process_time: CPU seconds, steadier on a loaded machine
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._depth = 0
        self.instrument = None

    @contextlib.contextmanager
    def timing(self, label: str):
        if self._depth == 0 and self.profiler is not None:
            self.profiler.disable()
        self._depth += 1
        t0 = self.clock()
        try:
            yield
        finally:
            self.seconds[label] = self.seconds.get(label, 0.0) + self.clock() - t0
            self.calls[label] = self.calls.get(label, 0) + 1
            self._depth -= 1
            if self._depth == 0 and self.profiler is not None:
                self.profiler.enable()

    def wrap(self, fn, label: str):
        def timed(*args, **kwargs):
            with self.timing(label):
                return fn(*args, **kwargs)
        return timed


class TimedInstrument:
    """An :class:`Instrument` that times every protocol call of the instrument it wraps
    (label ``instrument.<method>``; ``park`` apart: the engine parks after the run's wall
    time has stopped). Other attributes (the dry-run harness's truth) pass through untimed."""

    def __init__(self, inner: SimulatedAFM, watch: Stopwatch):
        self._inner = inner
        for name in PROTOCOL:
            setattr(self, name, watch.wrap(getattr(inner, name), "park" if name == "park" else f"instrument.{name}"))

    @property
    def config(self) -> InstrumentConfig:
        return self._inner.config

    def __getattr__(self, name):
        return getattr(self._inner, name)


@contextlib.contextmanager
def instrumented(watch: Stopwatch):
    """dry_run with a timed instrument, identification and planning timed apart."""
    saved = (dryrun.SimulatedAFM, assembly.identify, Replanner.start, Replanner.remainder,
             planner.plan_assembly, InstrumentClock.mode_switch)

    def make_sim(*args, **kwargs):
        sim = TimedInstrument(SimulatedAFM(*args, **kwargs), watch)
        assert isinstance(sim, Instrument)
        watch.instrument = sim
        return sim

    dryrun.SimulatedAFM = make_sim
    assembly.identify = watch.wrap(saved[1], "identify")
    Replanner.start = watch.wrap(saved[2], "plan")
    Replanner.remainder = watch.wrap(saved[3], "plan")
    planner.plan_assembly = watch.wrap(saved[4], "correction plan")   # looked up by course.correction
    InstrumentClock.mode_switch = watch.wrap(saved[5], "mode switch")  # counted: the simulator's charge
    try:
        yield
    finally:
        (dryrun.SimulatedAFM, assembly.identify, Replanner.start, Replanner.remainder,
         planner.plan_assembly, InstrumentClock.mode_switch) = saved


def grid_layout(area: float = 5000.0, rows: int = 2, cols: int = 3, pitch: float = 250.0,
                diameter: float = 90.0) -> Layout:
    """``rows`` x ``cols`` particle slots about the centre of a square working area."""
    c = area / 2
    targets = tuple(Target(f"g{i * cols + j + 1}", "particle",
                           (c + (j - (cols - 1) / 2) * pitch, c + (i - (rows - 1) / 2) * pitch), diameter)
                    for i in range(rows) for j in range(cols))
    return Layout((area, area), targets, name="grid")


def workloads(bowtie_seeds, random_seeds, particles: int):
    scene = load_scene(ROOT / "examples" / "bowtie_scene.toml")
    layout = load_layout(ROOT / "examples" / "bowtie.toml")
    for s in bowtie_seeds:
        yield "bowtie", s, scene, layout
    grid = grid_layout()
    for s in random_seeds:
        spec = SceneSpec(area=(5000.0, 5000.0), particles=particles, particle_diameter=(70.0, 110.0))
        yield f"random {particles}p", s, random_scene(spec, s), grid


def measure(name, seed, scene, layout, options, profiler=None) -> dict:
    watch = Stopwatch(profiler)
    with instrumented(watch):
        if profiler is not None:
            profiler.enable()
        out = dry_run(scene, layout, seed=seed, options=options)
        if profiler is not None:
            profiler.disable()
    s = out.summary
    pushes = out.report.counts.pushes
    sec = watch.seconds
    inst = sum(v for k, v in sec.items() if k.startswith("instrument."))
    overhead = s.wall["execute"] - inst
    timing = scene.params.timing
    lines = watch.calls.get("instrument.scan_line", 0)
    corr = sec.get("correction plan", 0.0)
    b = physical_bound(s.plan, options, scene.params.scanner, objects=s.env, timing=scene.params.timing)
    it = SimpleNamespace(**watch.instrument.ledger())    # the simulator's own split
    work = it.total - it.full_scan
    slots = len(s.plan.assignment)
    filled = len(out.filled)
    return {"name": name, "seed": seed, "pushes": pushes, "filled": filled, "slots": slots,
            "execute": s.wall["execute"], "instrument_wall": inst, "lines": lines,
            "settle": lines * timing.scan_line_overhead,
            "switch": watch.calls.get("mode switch", 0) * timing.mode_switch,
            "correction_plan": corr, "overhead": overhead / max(pushes, 1),
            "overhead_net": (overhead - corr) / max(pushes, 1),
            "identify": s.wall["identify"], "plan": s.wall["plan"], "it": it, "bound": b,
            "ratio": work / b.total_s if b.total_s > 0 else float("nan"),
            "ratio_slot": (work / filled) / (b.total_s / slots) if filled and slots and b.total_s > 0
            else float("nan")}


def profile_text(name, seed, scene, layout, options, top: int) -> tuple[str, dict]:
    prof = cProfile.Profile()
    row = measure(name, seed, scene, layout, options, prof)
    out = []
    for key in ("tottime", "cumulative"):
        buf = io.StringIO()
        st = pstats.Stats(prof, stream=buf)
        st.strip_dirs().sort_stats(key).print_stats(top)
        body = buf.getvalue()
        start = body.find("ncalls")
        out.append(f"By {key} (top {top}):\n\n```\n{body[start:].rstrip()}\n```")
    return "\n\n".join(out), row


def dac_figure(seconds: float, runs: int) -> tuple[float, float, float]:
    """bench_dac's workload at 100 kS/s, chunk 4096: median, min and max x real time."""
    config = InstrumentConfig(sample_rate=100_000.0)
    drift = LinearDrift(offset=(35.0, -20.0), velocity=(0.08, -0.05))
    moves = bench_dac.workload(config, seconds)
    ratios = [r[3] / r[1] for r in (bench_dac.run_once(moves, config, 4096, drift) for _ in range(runs))]
    return statistics.median(ratios), min(ratios), max(ratios)


def _med(rows, key) -> str:
    vals = [r[key] for r in rows if np.isfinite(r[key])]
    if not vals:
        return "n/a"
    return f"{statistics.median(vals):.3g} ({min(vals):.3g}-{max(vals):.3g})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bowtie-seeds", type=int, nargs="*", default=[1, 2, 3])
    ap.add_argument("--random-seeds", type=int, nargs="*", default=[1, 2, 3])
    ap.add_argument("--particles", type=int, default=30, help="particles of each generated scene")
    ap.add_argument("--dac-seconds", type=float, default=30.0, help="instrument seconds of the DAC workload")
    ap.add_argument("--dac-runs", type=int, default=3)
    ap.add_argument("--profile-top", type=int, default=25)
    ap.add_argument("--out", type=Path, default=HERE / "RESULTS_executor.md")
    args = ap.parse_args(argv)
    command = "python " + " ".join(shlex.quote(a) for a in [os.path.relpath(__file__), *(argv or sys.argv[1:])])
    options = ExecOptions()
    load0 = os.getloadavg()[0]

    rows = []
    for name, seed, scene, layout in workloads(args.bowtie_seeds, args.random_seeds, args.particles):
        rows.append(measure(name, seed, scene, layout, options))
        r = rows[-1]
        print(f"{name} seed {seed}: {r['pushes']} pushes, overhead {r['overhead'] * 1e3:.1f} ms/push, "
              f"instrument/bound {r['ratio']:.2f}", flush=True)
    first = next(workloads(args.bowtie_seeds[:1] or [3], [], args.particles))
    profile, prow = profile_text(*first, options, args.profile_top)
    dac, dac_lo, dac_hi = dac_figure(args.dac_seconds, args.dac_runs)

    machine = f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()}"
    over = statistics.median(r["overhead"] for r in rows)
    lines = [
        "# Executor: overhead per push, DAC rate, instrument time against the physical bound",
        "",
        f"Command: `{command}`  ",
        f"Date: {datetime.date.today().isoformat()}; code: {revision()}  ",
        f"Machine: {machine}; Python {platform.python_version()}, NumPy {np.__version__}; "
        f"shared with other jobs (load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end), "
        "so wall times are noisy: medians (min-max) of one run.",
        "",
        f"Dry-runs, strategy `{options.strategy.value}`: the bundled bowtie example, and generated scenes "
        f"of {args.particles} particles (70-110 nm) on 5 x 5 µm with a 2 x 3 grid of 90 nm slots "
        "(`grid_layout` in the script).",
        "",
        "## Summary",
        "",
        f"- executor overhead per push: median **{over * 1e3:.1f} ms** "
        f"(target <= {OVERHEAD_TARGET * 1e3:g} ms: {'met' if over <= OVERHEAD_TARGET else 'missed'}); "
        f"{_scaled(rows, 'overhead', 1e3)} ms over all runs; without correction planning "
        f"{_scaled(rows, 'overhead_net', 1e3)} ms",
        f"- DAC sample generation at 100 kS/s (bench_dac workload, {args.dac_seconds:g} s, chunk 4096): "
        f"**{dac:.1f}x** real time ({dac_lo:.1f}-{dac_hi:.1f}; target >= {DAC_TARGET:g}x: "
        f"{'met' if dac >= DAC_TARGET else 'missed'})",
        f"- instrument time (less the full scan) over the physical bound of the first plan: "
        f"median **{statistics.median(r['ratio'] for r in rows):.2f}** ({_med(rows, 'ratio')}); per filled slot "
        f"{_med(rows, 'ratio_slot')}; of the instrument time above the bound, the simulator's tapping/contact "
        f"mode switches take {_share(rows, 'switch')} %, settling before scan lines {_share(rows, 'settle')} %, "
        "and the rest (scan lines longer and more numerous than the minimum, reference and bootstrap scans "
        f"of the drift filter, re-pushes, lowering and lifting) {_share(rows, None)} % (medians)",
        "",
        "## Per run",
        "",
        "Wall seconds: identification and planning (not the executor's), execute (the procedure less "
        "those two), inside the instrument, "
        "correction planning (inside execute); overhead = (execute - instrument) / pushes. Instrument "
        "seconds by the simulator's ledger (`SimulatedAFM.ledger()`; the report's split is the executor's "
        "own count, which leaves the switches into contact mode out): total, full scan, local scan, push, "
        "travel; of these, the simulator's settling before "
        "each scan line (`scan_line_overhead` x lines) and its tapping/contact mode switches "
        "(`mode_switch` x switches), both outside the bound; bound: push + scan + travel "
        "(`executor/bound.py`).",
        "",
        "| scene | seed | pushes | filled/slots | identify s | plan s | execute s | instrument s | corr. plan s | overhead ms/push "
        "| w/o corr. ms | inst. total | full scan | local scan | push | travel | lines | settling "
        "| mode switches | bound push | bound scan | bound travel | bound | (inst - full)/bound | per slot |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
        "| ---: | ---: "
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        it, b = r["it"], r["bound"]
        lines.append(
            f"| {r['name']} | {r['seed']} | {r['pushes']} | {r['filled']}/{r['slots']} | {r['identify']:.2f} "
            f"| {r['plan']:.1f} | {r['execute']:.2f} "
            f"| {r['instrument_wall']:.2f} | {r['correction_plan']:.2f} | {r['overhead'] * 1e3:.1f} "
            f"| {r['overhead_net'] * 1e3:.1f} | {it.total:.0f} | {it.full_scan:.0f} | {it.local_scan:.1f} "
            f"| {it.push:.1f} | {it.travel:.1f} | {r['lines']} | {r['settle']:.1f} | {r['switch']:.0f} "
            f"| {b.push_s:.1f} | {b.scan_s:.2f} | {b.travel_s:.2f} "
            f"| {b.total_s:.1f} | {r['ratio']:.2f} | {r['ratio_slot']:.2f} |")
    lines += [
        "",
        "## Where the executor's own time goes",
        "",
        f"{first[0]} seed {first[1]} once more under cProfile, paused while the instrument, identification "
        f"and planning run (correction planning included), so only the executor's own work (and the "
        f"dry-run harness around it) is profiled: {prow['pushes']} pushes, overhead "
        f"{prow['overhead'] * 1e3:.1f} ms per push under the profiler.",
        "",
        profile,
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.write_text(text, encoding="utf-8")
    print(f"written to {args.out}")
    return 0


def revision() -> str:
    """The checkout's commit, and whether tracked files differ from it."""
    def git(*args):
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True).stdout.strip()
    try:
        rev = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except OSError:
        return "unknown"
    return (rev + (" with uncommitted changes" if dirty else "")) if rev else "unknown"


def _share(rows, key) -> str:
    """Median percentage of the instrument time above the bound taken by ``key`` (None: the rest)."""
    shares = []
    for r in rows:
        excess = r["it"].total - r["it"].full_scan - r["bound"].total_s
        part = excess - r["switch"] - r["settle"] if key is None else r[key]
        shares.append(100.0 * part / excess)
    return f"{statistics.median(shares):.0f}"


def _scaled(rows, key, scale) -> str:
    vals = [r[key] * scale for r in rows]
    return f"{min(vals):.1f}-{max(vals):.1f}"


if __name__ == "__main__":
    raise SystemExit(main())
