"""Wall time of the bundled bowtie's first plan (issue 14 asks for 3 s).

    python bench/bench_first_plan.py --seeds none,1,4 --reps 3

Each run is ``nanoasm dry-run [--seed S]`` in a fresh process, stopped right after its
first ``plan_assembly`` (the full scan and identification before it are not timed).
Prints one line per run and the medians; the machine is shared and noisy.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

#: Run in the child: time the first plan_assembly, then end the process.
CHILD = """
import os, sys, time
from nanoasm.planner import core
import nanoasm.planner as P, nanoasm.planner.replan as R
orig = core.plan_assembly
def first(*a, **k):
    t = time.perf_counter(); orig(*a, **k)
    print(f"FIRST_PLAN {time.perf_counter() - t:.3f}", flush=True); os._exit(0)
core.plan_assembly = P.plan_assembly = R.plan_assembly = first
from nanoasm import cli
sys.argv = ["nanoasm", "dry-run", *sys.argv[1:]]
cli.main()
"""


def first_plan(seed: str, report: str) -> float:
    args = [] if seed == "none" else ["--seed", seed]
    out = subprocess.run([sys.executable, "-c", CHILD, *args, "--report", report], capture_output=True, text=True)
    for line in out.stdout.splitlines():
        if line.startswith("FIRST_PLAN"):
            return float(line.split()[1])
    raise RuntimeError(f"no plan timed (seed {seed}): {out.stderr.strip()[-300:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="none,1,4", help="world seeds; none: the bundled run")
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args()
    report = os.path.join(os.environ.get("TMPDIR", "/tmp"), f"first_plan_{os.getpid()}.json")
    times: dict[str, list[float]] = {}
    for rep in range(a.reps):
        for seed in a.seeds.split(","):
            t = first_plan(seed, report)
            times.setdefault(seed, []).append(t)
            print(f"rep {rep + 1} seed {seed}: {t:.2f} s", flush=True)
    print(f"medians ({time.strftime('%Y-%m-%d')}):")
    for seed, ts in times.items():
        print(f"  seed {seed}: {statistics.median(ts):.2f} s (range {min(ts):.2f}-{max(ts):.2f})")


if __name__ == "__main__":
    main()
