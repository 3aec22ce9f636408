"""Run-log overhead: wall time of a dry-run with and without its MCAP log, and log size.

Dry-runs the bundled bowtie's particle slots (the rod slot left out so a run takes a few
seconds) ``--runs`` times without a log and ``--runs`` times with one (alternating, so
both see the same machine load), through ``dry_run`` as ``nanoasm dry-run --log`` does,
and reports medians: wall time, the overhead, the log's size and its size per push, and
the time to read the log back and review it. Writes the figures to ``--out``.

    python bench/bench_runlog.py                   # 5 runs each, seed 3, strategy full
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shlex
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from nanoasm.cad.layout import load_layout
from nanoasm.dryrun import dry_run
from nanoasm.examples import path as example
from nanoasm.executor.logread import read_log
from nanoasm.executor.runlog import RunLog
from nanoasm.executor.strategy import ExecOptions
from nanoasm.review import review
from nanoasm.world.scene import load_scene


def once(scene, layout, seed: int, strategy: str, log_path: Path | None) -> tuple[float, int, list[int]]:
    """(wall seconds, pushes, log size after each checkpoint) of one dry-run, logged to
    ``log_path`` when given."""
    t0 = time.perf_counter()
    subs, grown = [], []
    if log_path is not None:
        def size(topic: str, doc: dict) -> None:     # after the RunLog, which flushed at the checkpoint
            if topic == "checkpoint":
                grown.append(log_path.stat().st_size)

        subs = [RunLog(log_path, layout=layout, metadata={"kind": "dry-run", "seed": seed, "strategy": strategy},
                       truth=True), size]
    try:
        out = dry_run(scene, layout, seed=seed, options=ExecOptions(strategy=strategy), subscribers=subs)
    finally:
        if subs:
            subs[0].close()
    return time.perf_counter() - t0, out.report.counts.pushes, grown


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--strategy", default="full")
    ap.add_argument("--out", type=Path, default=Path(__file__).with_name("RESULTS_runlog.md"))
    args = ap.parse_args()

    layout = load_layout(example("bowtie.toml"))
    layout = replace(layout, targets=tuple(t for t in layout.targets if t.kind == "particle"))
    scene = load_scene(example("bowtie_scene.toml"))
    once(scene, layout, args.seed, args.strategy, None)          # warm-up: imports, caches
    plain, logged, sizes, pushes, reads, reviews, per_push = [], [], [], [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            plain.append(once(scene, layout, args.seed, args.strategy, None)[0])
            path = Path(tmp) / f"run{i}.mcap"
            wall, n, grown = once(scene, layout, args.seed, args.strategy, path)
            logged.append(wall)
            if len(grown) > 1:                  # what one more push adds, on disk
                per_push.append((grown[-1] - grown[0]) / (len(grown) - 1))
            sizes.append(path.stat().st_size)
            pushes.append(n)
            t0 = time.perf_counter()
            log = read_log(path)
            reads.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            review(path)
            reviews.append(time.perf_counter() - t0)
            messages = len(log.messages)
            first = grown[0]
    med = statistics.median
    overhead = med(logged) - med(plain)
    n_push = med(pushes)
    rows = [
        ("dry-run without log, wall s", f"{med(plain):.2f}", f"{min(plain):.2f}-{max(plain):.2f}"),
        ("dry-run with --log, wall s", f"{med(logged):.2f}", f"{min(logged):.2f}-{max(logged):.2f}"),
        ("overhead of the log, s (% of the run)", f"{overhead:+.2f} ({100 * overhead / med(plain):+.1f} %)", ""),
        ("pushes per run", f"{n_push:g}", ""),
        ("log size, kB", f"{med(sizes) / 1e3:.0f}", f"{min(sizes) / 1e3:.0f}-{max(sizes) / 1e3:.0f}"),
        ("log size at the first checkpoint (full scan, set-up, one push), kB", f"{first / 1e3:.0f}", ""),
        ("log size per further push, kB", f"{med(per_push) / 1e3:.1f}",
         f"{min(per_push) / 1e3:.1f}-{max(per_push) / 1e3:.1f}"),
        ("messages in the log", f"{messages}", ""),
        ("read_log, ms", f"{1e3 * med(reads):.0f}", f"{1e3 * min(reads):.0f}-{1e3 * max(reads):.0f}"),
        ("review (read and summarise), ms", f"{1e3 * med(reviews):.0f}",
         f"{1e3 * min(reviews):.0f}-{1e3 * max(reviews):.0f}"),
    ]
    for name, value, spread in rows:
        print(f"{name:40s} {value:>16s}  {spread}")
    cmd = "python bench/bench_runlog.py" + "".join(f" {shlex.quote(a)}" for a in sys.argv[1:])
    lines = [
        "# Run-log overhead",
        "",
        f"Command: `{cmd}`  ",
        f"Date: {datetime.date.today().isoformat()}  ",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.system()}; Python "
        f"{platform.python_version()}, NumPy {np.__version__}",
        "",
        f"Workload: the bundled bowtie's 6 particle slots in `examples/bowtie_scene.toml`, seed {args.seed}, "
        f"strategy {args.strategy}; `dry_run` with and without a `RunLog` subscriber (as `nanoasm dry-run "
        f"--log`), {args.runs} runs each, alternating. Medians, (min-max).",
        "",
        "| figure | median | (min-max) |",
        "| --- | ---: | ---: |",
        *(f"| {name} | {value} | {spread} |" for name, value, spread in rows),
        "",
    ]
    args.out.write_text("\n".join(lines))
    print(f"{args.out}: written")


if __name__ == "__main__":
    main()
