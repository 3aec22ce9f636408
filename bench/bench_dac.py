"""DAC sample generation rate against real time.

Plans and streams a realistic push/travel mix (lifted travel between random objects,
pushes of one to three segments at a push speed, a linear drift prediction) worth
``--seconds`` of instrument time at ``--rate`` samples/s, through every check the
executor's stream passes, and reports the median of ``--runs`` runs as a ratio to real
time (target: at least 20x at 100 kS/s). Writes the figures to ``--out``.

    python bench/bench_dac.py                      # 60 s at 100 kS/s, 5 runs
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from nanoasm.executor.dac import plan_dac
from nanoasm.executor.dac_frames import LinearDrift
from nanoasm.executor.trajectory import operation
from nanoasm.instrument import InstrumentConfig

TARGET = 20.0


def workload(config: InstrumentConfig, seconds: float, seed: int = 7):
    """Operations whose plan lasts at least ``seconds`` of instrument time: pushes of one
    to three 0.3-2 µm segments at 10 µm/s, between objects up to 30 µm apart."""
    rng = np.random.default_rng(seed)
    moves, here = [], np.array([45000.0, 45000.0])
    while not moves or plan_dac(moves, config, config.rest_codes()).duration < seconds:
        start = np.clip(here + rng.uniform(-30000, 30000, 2), 5000, 85000)
        k = int(rng.integers(1, 4))
        heading = rng.uniform(0, 2 * np.pi) + rng.uniform(-0.3, 0.3, k)
        steps = rng.uniform(300, 2000, k)[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
        push = np.vstack([start, start + np.cumsum(steps, axis=0)])
        moves += operation(push, push_speed=10000.0)
        here = push[-1]
    return moves


def run_once(moves, config, chunk: int, drift) -> tuple[float, float, int, float]:
    """(plan seconds, total wall seconds, samples, instrument seconds)."""
    t0 = time.perf_counter()
    plan = plan_dac(moves, config, config.rest_codes(), drift=drift)
    t1 = time.perf_counter()
    n = 0
    for c in plan.chunks(chunk):
        n += len(c)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t0, n, plan.duration


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="instrument seconds to generate")
    ap.add_argument("--rate", type=float, default=100_000.0, help="DAC sample rate, Hz")
    ap.add_argument("--chunks", type=int, nargs="+", default=[4096, 1024, 16384], help="chunk sizes")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path(__file__).with_name("RESULTS_dac.md"))
    args = ap.parse_args(argv)
    command = "python " + " ".join(shlex.quote(a) for a in [os.path.relpath(__file__), *(argv or sys.argv[1:])])

    config = InstrumentConfig(sample_rate=args.rate)
    drift = LinearDrift(offset=(35.0, -20.0), velocity=(0.08, -0.05))
    moves = workload(config, args.seconds)
    rows = []
    for chunk in args.chunks:
        runs = [run_once(moves, config, chunk, drift) for _ in range(args.runs)]
        plan_s, wall = statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)
        n, sim = runs[0][2], runs[0][3]
        ratios = [r[3] / r[1] for r in runs]
        rows.append((chunk, n, sim, plan_s, wall, sim / wall, n / wall, min(ratios), max(ratios)))

    machine = f"{platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.system()}"
    versions = f"Python {platform.python_version()}, NumPy {np.__version__}"
    n_ops = sum(m.kind == "push" for m in moves)
    lines = [
        "# DAC sample generation rate",
        "",
        f"Command: `{command}`  ",
        f"Date: {datetime.date.today().isoformat()}  ",
        f"Machine: {machine}; {versions}",
        "",
        f"Workload: {n_ops} push operations (travel lifted, lower, push at 10 µm/s, lift), "
        f"linear drift, default scanner limits, {args.rate:g} samples/s; plan and stream with "
        f"every chunk through `check_samples`. Median of {args.runs} runs; target >= {TARGET:g}x real time.",
        "",
        "| chunk | samples | instrument s | plan ms | wall s | x real time | (min-max) | samples/s |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for chunk, n, sim, plan_s, wall, ratio, rate, lo, hi in rows:
        lines.append(f"| {chunk} | {n} | {sim:.2f} | {plan_s * 1e3:.1f} | {wall:.3f} | {ratio:.1f} "
                     f"| {lo:.0f}-{hi:.0f} | {rate:.3g} |")
    ok = rows[0][5] >= TARGET
    lines += ["", f"Chunk {rows[0][0]}: {rows[0][5]:.1f}x real time, "
              f"{'meets' if ok else 'misses'} the {TARGET:g}x target."]
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.write_text(text, encoding="utf-8")
    print(f"written to {args.out}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
