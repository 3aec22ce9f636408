"""Scale: dry-runs of 10 to 1000 objects, compute time per push by stage, peak memory, log size.

Dry-runs (``nanoasm.dryrun.dry_run``, full strategy, logged to MCAP as ``nanoasm dry-run
--log`` logs) of the ``scaleN`` scene family (``nanoasm.world.families.scale_family``: N
particles of 80-100 nm at a constant density, 1000 in 40 x 40 µm, the largest area a run
full-scans; ``round(0.3 N)`` particle slots in a square grid spread over the area). Each
run is its own process (``--one N SEED``), so its peak resident memory (``ru_maxrss``) is
its own. Per run:

- **compute time per push by stage** (CPU seconds of the process, ``time.process_time``:
  the machine is shared, and CPU time does not count the waits for a core that wall time
  does; on an idle machine the two agree): identification (``identify`` of the full scan),
  planning (the first plan, ``Replanner.start``), replanning (``Replanner.remainder`` and
  the executor's correction plans), the simulator (every call of the ``Instrument``
  protocol into the ``SimulatedAFM``: its physics, rendering and drift; timed by
  ``bench_executor``'s proxy) and the executor (the rest of the run's time: the run
  engine, local-scan analysis, drift filter, run log, the harness's truth); each over
  the pushes made. The target at 1000 objects, 50 ms per push, is for all but the simulator.
- **replanning per remaining object**: each replan's time over the objects its new
  plan still pushes; the median and the largest over the run's replans.
- **peak memory** (MB) and the **log size** (MB, the ``.mcap``; the simulated world kept
  beside it for resuming is not written here).
- **fill**: slots the truth finds filled (``Outcome.truly_filled``) over slots.

    python bench/bench_scale.py                         # writes bench/RESULTS_scale.md and scale.png
    python bench/bench_scale.py --sizes 10,30,100 --seeds 1-3 --out /tmp/r.md
    python bench/bench_scale.py --one 300 1             # one run, its row as JSON
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

SIZES = (10, 30, 100, 300, 1000)
SEEDS = (1, 2, 3)
#: Per-push time target at 1000 objects, simulator excluded (s); replanning per
#: remaining object (s); peak memory (MB); fill.
TARGETS = {"push": 0.050, "replan_per_object": 0.020, "memory_mb": 1024, "fill": 0.95}
STAGES = ("identify", "plan", "replan", "executor", "simulator")


def measure(n: int, seed: int, log_dir: Path) -> dict:
    """One dry-run of ``scale{n}`` at ``seed``; its row."""
    import bench_executor as be

    import nanoasm.dryrun as dryrun
    import nanoasm.executor.assembly as assembly
    import nanoasm.planner as planner
    from nanoasm.executor.runlog import RunLog
    from nanoasm.planner.replan import Replanner
    from nanoasm.world.families import family_case
    from nanoasm.world.sim import SimulatedAFM

    scene, layout = family_case(f"scale{n}", seed)
    watch = be.Stopwatch(clock=time.process_time)      # CPU seconds: the machine is shared
    replans: list[tuple[float, int]] = []
    saved = (dryrun.SimulatedAFM, assembly.identify, Replanner.start, Replanner.remainder, planner.plan_assembly)

    def make_sim(*args, **kwargs):
        sim = be.TimedInstrument(SimulatedAFM(*args, **kwargs), watch)
        watch.instrument = sim
        return sim

    def remainder(self, *args, **kwargs):
        t0 = time.process_time()
        with watch.timing("replan"):
            rest = saved[3](self, *args, **kwargs)
        if rest.replanned:
            replans.append((time.process_time() - t0, len({op.object for op in rest.plan.operations})))
        return rest

    dryrun.SimulatedAFM = make_sim
    assembly.identify = watch.wrap(saved[1], "identify")
    Replanner.start = watch.wrap(saved[2], "plan")
    Replanner.remainder = remainder
    planner.plan_assembly = watch.wrap(saved[4], "correction")     # looked up by course.correction
    log_path = log_dir / f"scale{n}-{seed}.mcap"
    log = RunLog(log_path, layout=layout, metadata={"kind": "dry-run", "seed": seed, "strategy": "full"}, truth=True)
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        out = dryrun.dry_run(scene, layout, seed=seed, subscribers=[log])
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        log.close()
        (dryrun.SimulatedAFM, assembly.identify, Replanner.start, Replanner.remainder,
         planner.plan_assembly) = saved
    sec = watch.seconds
    stages = {"identify": sec.get("identify", 0.0), "plan": sec.get("plan", 0.0),
              "replan": sec.get("replan", 0.0) + sec.get("correction", 0.0),
              "simulator": sum(v for k, v in sec.items() if k.startswith("instrument."))}
    stages["executor"] = cpu - sum(stages.values())
    pushes = out.report.counts.pushes
    per_object = [dt / max(k, 1) for dt, k in replans]
    return {"n": n, "seed": seed, "objects": len(scene.objects), "slots": len(layout.targets),
            "area_um": scene.area[0] / 1000.0, "pushes": pushes, "replans": len(replans),
            "wall_s": wall, "cpu_s": cpu, **{f"{k}_s": v for k, v in stages.items()},
            **{f"{k}_per_push_ms": 1e3 * v / max(pushes, 1) for k, v in stages.items()},
            "push_ms": 1e3 * (cpu - stages["simulator"]) / max(pushes, 1),
            "replan_per_object_ms": 1e3 * statistics.median(per_object) if per_object else None,
            "replan_per_object_max_ms": 1e3 * max(per_object) if per_object else None,
            "memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "log_mb": log_path.stat().st_size / 1e6,
            "fill": len(out.truly_filled) / len(layout.targets),
            "verdict_fill": len(out.verdict_filled) / len(layout.targets),
            "instrument_h": out.report.instrument_time.total / 3600.0}


#: What the profiles showed and what was changed (issue 16, item 5), kept with the figures.
NOTES = """## What did not scale, and what was changed

Profiled first (cProfile of `dry_run` on `scale300` seed 1, before the changes, 243
pushes, 54 s wall at a load average of 4 on 2 cores; and memory of the full scan,
identification and window choice on `scale1000`, tracemalloc and `ru_maxrss`):

| cost | before | after | change |
| --- | ---: | ---: | --- |
| scan lines: `render_line` made every body's image function for every line, O(N) Python per line | 5.1 s (958 lines) | 0.65 s | `world/render.py` `surface_near`: the bodies whose image can reach the line, one array test on the contact cores (`world/sim/afm.py`); heights bit-identical |
| planning: `FreeSpace` remade every object's shapely geometry after every planned push, O(N) per push | 4.0 s of 6.2 s planning | 0.35 s | `planner/freespace.py`: `move` replaces the moved body's core alone, the STRtree is rebuilt from the kept array; same queries, same answers |
| simulator's creep: a sum over every move ever made, per query | 0.9 s (1750 queries; grows as N²) | O(1) per query beyond 4096 moves | `world/sim/creep_sum.py`: moves older than a window folded into a power series about a time on a grid, exact to float rounding (1e-16 of the steps); direct, bit-identical, below 4096 foldable moves |
| simulator's `candidates()`: a box test of every unit per chunk | 0.16 s (1044 calls) | grid cells only | `world/sim/push_support.py` via the contact space's uniform grid (`ContactSpace.units_near`); same objects |
| memory, window choice (`executor/windows.py`) on a 4000-pixel scan | 2.1 GB traced | see peak MB above | correlations in bands of rows, products made band by band, the strided results copied (a view kept every full correlation alive) |
| memory, full-scan rendering (`world/render.py`) | 640 MB traced | 256 MB | the substrate evaluated in bands of rows; image bit-identical |

Not changed here (files other sessions are changing, or beyond this change):

- **relocalisation** (`executor/relocalise.py` `_mask`): each relocalisation masks the
  whole full scan around every object pushed so far, a Python loop over the objects with
  four full-image float arrays per object (the pixel coordinates alone are 256 MB at 4000 x
  4000 pixels): O(pixels x pushed objects) per relocalisation, quadratic in N. The
  `scale1000` run spent its time there (every py-spy sample of a minute, 03:00) and did
  not finish within 30 min on the loaded machine; with the relocalisation's mask made
  on the window's pixels only (or with a distance transform of the moved footprints),
  this goes away.
- **identification** (`world/identify`) costs about 84 s and 850 MB (traced) on the
  4000 x 4000 pixel scan of 1000 objects, 90 % of it in levelling (row medians, robust
  sigma, surface fits over full-size float copies): linear in the scanned area and done
  once, but at N = 1000 it sets the peak memory before the first push.
- **checkpoints and the run log**: every push's checkpoint serialises the whole belief
  and the references (about 110 kB at N = 100, 15 ms a push at N = 300), so the log
  grows as N² (74 MB at N = 300; at N = 1000 near the 1 GiB a log may hold,
  `MAX_LOG_BYTES`); the executor's `environment()` and reference choice are O(N) a push
  too. They make the executor's cost a push rise from 37 ms (N = 30-100) to 53 ms (N = 300).
- **fill**: the table's fill is the truth's (`truly_filled`: the slots true objects fill).
  The dry-run's own `filled` (by the run's assignment) counted fewer on large areas (72 of
  90 on `scale300` seed 1, whose truth fills 90 and whose check scans 89) while `match_ids`
  paired identified and true objects by their raw full-scan positions, which the drift over
  a long full scan had moved by more than their spacing (on `wide` seed 6, 800 nm); it now
  takes each row's true drift out first (`nanoasm.dryrun.row_drift`).
"""


def run_one(n: int, seed: int, timeout: float) -> dict:
    """``measure`` in a fresh process (its own peak memory); a row with ``error`` on failure."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--one", str(n), str(seed), "--log-dir", tmp]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT)
        except subprocess.TimeoutExpired:
            return {"n": n, "seed": seed, "error": f"timed out after {timeout:g} s"}
    if done.returncode != 0:
        return {"n": n, "seed": seed, "error": (done.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def med(rows: list[dict], key: str):
    vals = [r[key] for r in rows if r.get(key) is not None]
    return statistics.median(vals) if vals else None


def fmt(v, digits: int = 3) -> str:
    return "-" if v is None else f"{v:.{digits}g}" if isinstance(v, float) else str(v)


COLUMNS = (("n", "N objects", 0), ("slots", "slots", 0), ("area_um", "side µm", 3), ("pushes", "pushes", 0),
           ("identify_per_push_ms", "identify", 2), ("plan_per_push_ms", "plan", 2),
           ("replan_per_push_ms", "replan", 2), ("executor_per_push_ms", "executor", 2),
           ("push_ms", "all but the simulator", 2), ("simulator_per_push_ms", "simulator", 3),
           ("replan_per_object_ms", "replan per remaining object, ms", 2), ("memory_mb", "peak MB", 3),
           ("log_mb", "log MB", 3), ("fill", "fill", 3), ("cpu_s", "run CPU s", 3), ("wall_s", "run wall s", 3))


def table(rows: list[dict], sizes) -> str:
    lines = ["| " + " | ".join(h for _, h, _ in COLUMNS) + " |", "|" + " ---: |" * len(COLUMNS)]
    for n in sizes:
        ok = [r for r in rows if r["n"] == n and "error" not in r]
        if ok:
            lines.append("| " + " | ".join(fmt(med(ok, k), d) if d else fmt(ok[0][k]) if k in ("n", "slots")
                                           else fmt(med(ok, k), 3) for k, _, d in COLUMNS) + " |")
    return "\n".join(lines)


def plot(rows: list[dict], sizes, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ns = [n for n in sizes if any(r["n"] == n and "error" not in r for r in rows)]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    for k in STAGES:
        ax.plot(ns, [med([r for r in rows if r["n"] == n and "error" not in r], f"{k}_per_push_ms") for n in ns],
                "o-", label=k)
    ax.plot(ns, [med([r for r in rows if r["n"] == n and "error" not in r], "push_ms") for n in ns], "k--",
            label="all but the simulator")
    ax.axhline(1e3 * TARGETS["push"], color="grey", lw=0.8, ls=":")
    ax.set(xscale="log", yscale="log", xlabel="objects N", ylabel="CPU ms per push (median over seeds)")
    ax.legend(fontsize=8)
    for key, label in (("memory_mb", "peak memory, MB"), ("log_mb", "log, MB")):
        bx.plot(ns, [med([r for r in rows if r["n"] == n and "error" not in r], key) for n in ns], "o-", label=label)
    bx.set(xscale="log", yscale="log", xlabel="objects N")
    bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)), help="object counts N, comma-separated")
    ap.add_argument("--seeds", default="1-3", help="seeds, e.g. 1-3 (each N)")
    ap.add_argument("--big-seeds", default=None, help="seeds for N >= 1000 (default: --seeds)")
    ap.add_argument("--timeout", type=float, default=1200.0, help="seconds per run")
    ap.add_argument("--out", type=Path, default=HERE / "RESULTS_scale.md")
    ap.add_argument("--one", nargs=2, type=int, metavar=("N", "SEED"), help="one run; print its row as JSON")
    ap.add_argument("--log-dir", type=Path, default=None)
    ap.add_argument("--rows", type=Path, nargs="+", help="write the results of these files of rows (the JSON "
                    "lines this script prints, e.g. from runs made apart) instead of running")
    args = ap.parse_args(argv)
    if args.one:
        with tempfile.TemporaryDirectory() as tmp:
            row = measure(*args.one, args.log_dir or Path(tmp))
        print(json.dumps(row))
        return
    from nanoasm.sweep import parse_seeds

    sizes = [int(v) for v in args.sizes.split(",")]
    if args.rows:
        rows = [json.loads(line) for f in args.rows for line in f.read_text().splitlines() if line.startswith("{")]
        write(sorted(rows, key=lambda r: (r["n"], r["seed"])), sizes, args)
        return
    seeds = parse_seeds(args.seeds)
    big = parse_seeds(args.big_seeds) if args.big_seeds else seeds
    rows = []
    for n in sizes:
        for seed in (big if n >= 1000 else seeds):
            row = run_one(n, seed, args.timeout)
            rows.append(row)
            print(json.dumps(row), flush=True)
    write(rows, sizes, args)


def write(rows: list[dict], sizes, args) -> None:
    import numpy as np

    png = args.out.with_name("scale.png")
    plot(rows, sizes, png)
    ok = [r for r in rows if "error" not in r]
    errors = [r for r in rows if "error" in r]
    cmd = "python bench/bench_scale.py" + "".join(f" {shlex.quote(a)}" for a in sys.argv[1:])
    if args.rows:       # the rows of runs made apart: the one command that makes them all
        cmd = (f"python bench/bench_scale.py --sizes {args.sizes} --seeds {args.seeds}"
               + (f" --big-seeds {args.big_seeds}" if args.big_seeds else ""))
    big = [r for r in ok if r["n"] == max(sizes)]
    lines = [
        "# Scale: dry-runs from 10 to 1000 objects", "",
        f"Command: `{cmd}`  ",
        f"Date: {datetime.date.today().isoformat()}  ",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores (shared with other work), {platform.system()}; "
        f"Python {platform.python_version()}, NumPy {np.__version__}", "",
        __doc__.split("\n\n    python")[0].strip(), "",
        "Medians over the seeds of each N (ms per push unless said); every run's row below.", "",
        table(ok, sizes), "",
        f"![cost against N]({png.name})", "",
    ]
    if big:
        n = big[0]["n"]
        lines += [f"Targets at N = {n}: all but the simulator {fmt(med(big, 'push_ms'))} ms per push (target "
                  f"{1e3 * TARGETS['push']:g}), replanning {fmt(med(big, 'replan_per_object_ms'))} ms per remaining "
                  f"object (target {1e3 * TARGETS['replan_per_object']:g}), peak memory {fmt(med(big, 'memory_mb'))} MB "
                  f"(target {TARGETS['memory_mb']}), fill {fmt(med(big, 'fill'))} (target {TARGETS['fill']}).", ""]
    lines += [NOTES, "Every run:", "", "```"] + [json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                                                       for k, v in r.items()}) for r in rows] + ["```", ""]
    if errors:
        lines += [f"{len(errors)} run(s) failed: " + "; ".join(f"N={r['n']} seed {r['seed']}: {r['error']}"
                                                              for r in errors), ""]
    args.out.write_text("\n".join(lines))
    print(f"{args.out}: written; {png}")


if __name__ == "__main__":
    main()
