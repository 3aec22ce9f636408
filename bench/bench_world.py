"""Simulated AFM speed: pushing physics among many objects, full scans, lifted travel.

- physics step rate: a 40 x 40 µm sample with ``--objects`` particles (default 1000); one
  of them is pushed 2 µm at 200 nm/s (one physics step per DAC sample near it, the
  others idle); steps per wall second of the contact part (target >= 1e4 steps/s);
- full scan: ``pixels`` x ``pixels`` (512) of a 5 x 5 µm sample with 80 particles and 20
  rods, tip dilation, roughness, noise, line offsets and drift (target <= 0.5 s);
- lifted travel: a 40-line raster over the 1000-object sample at the lift height, DAC
  samples per wall second (idle objects should cost nothing).

Medians of ``--runs`` runs; writes the table to ``--out``.

    python bench/bench_world.py                    # 5 runs, writes bench/RESULTS_world.md
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from nanoasm.instrument import InstrumentConfig, ramp
from nanoasm.world.cantilever import tip_offset
from nanoasm.world.random_scene import SceneSpec, random_scene
from nanoasm.world.sim import SimulatedAFM, lever_from_params

STEP_TARGET, SCAN_TARGET = 1.0e4, 0.5


def _codes(sim: SimulatedAFM, points, push_speed: float) -> list[np.ndarray]:
    cfg, cur, out = sim.config, sim.position(), []
    for i, p in enumerate(points):
        c = cfg.nm_to_codes(np.asarray(p, float))
        pushing = i > 0 and p[2] < 0 and points[i - 1][2] < 0
        out.append(ramp(cur, c, cfg, speed=push_speed if pushing else None))
        cur = c
    return out


def physics_run(objects: int, seed: int, dac_bits: int = 16) -> tuple[float, int, float]:
    """(wall seconds of the contact part, physics steps in it, distance the target moved)."""
    scene = random_scene(SceneSpec(area=(40000.0, 40000.0), particles=objects, gap=100.0), seed)
    params = dataclasses.replace(scene.params, scanner=InstrumentConfig(dac_bits=dac_bits))
    sim = SimulatedAFM(scene, seed=seed, params=params)
    target = min(scene.objects, key=lambda b: (b.at[0] - 20000) ** 2 + (b.at[1] - 20000) ** 2)
    cfg, p = sim.config, sim.params
    off = tip_offset(cfg.preload / p.cantilever.K_n, 0.0, cfg.scan_angle, lever_from_params(p))[:2]
    x0, y = target.at[0] - target.radius - 80.0 - off[0], target.at[1] - off[1]
    travel, lower, push, lift = _codes(sim, [(x0, y, cfg.lift), (x0, y, -cfg.preload),
                                             (x0 + 2000.0, y, -cfg.preload), (x0 + 2000.0, y, cfg.lift)], 200.0)
    sim.write(travel)
    steps = sim.diagnostics()["steps"]
    t = time.perf_counter()
    sim.write(np.vstack([lower, push]))
    wall = time.perf_counter() - t
    steps = sim.diagnostics()["steps"] - steps
    sim.write(lift)
    moved = np.hypot(*np.subtract(sim.truth()[scene.objects.index(target)].at, target.at))
    return wall, steps, float(moved)


def scan_run(pixels: int, seed: int) -> float:
    scene = random_scene(SceneSpec(area=(5000.0, 5000.0), particles=80, rods=20, gap=30.0), seed)
    sim = SimulatedAFM(scene, seed=seed)
    t = time.perf_counter()
    sim.full_scan(pixels)
    return time.perf_counter() - t


def travel_run(objects: int, seed: int) -> tuple[float, int]:
    scene = random_scene(SceneSpec(area=(40000.0, 40000.0), particles=objects, gap=100.0), seed)
    sim = SimulatedAFM(scene, seed=seed)
    lift = sim.config.lift
    pts = [(x, 500.0 if k % 2 == 0 else 39500.0, lift) for k, x in enumerate(np.linspace(500, 39500, 40))]
    codes = np.vstack(_codes(sim, pts, 200.0))
    t = time.perf_counter()
    sim.write(codes)
    return time.perf_counter() - t, len(codes)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--objects", type=int, default=1000)
    ap.add_argument("--pixels", type=int, default=512)
    ap.add_argument("--out", default=str(Path(__file__).with_name("RESULTS_world.md")))
    args = ap.parse_args(argv)

    phys = [physics_run(args.objects, 11 + r) for r in range(args.runs)]
    rates = [n / w for w, n, _ in phys]
    fine = [physics_run(args.objects, 11 + r, dac_bits=20) for r in range(args.runs)]
    f_rates = [n / w for w, n, _ in fine]
    scans = [scan_run(args.pixels, 21 + r) for r in range(args.runs)]
    travel = [travel_run(args.objects, 31 + r) for r in range(args.runs)]
    t_rates = [n / w for w, n in travel]

    step_rate, scan_s, travel_rate = statistics.median(rates), statistics.median(scans), statistics.median(t_rates)
    fine_rate = statistics.median(f_rates)
    rows = [
        (f"physics steps/s, 1 of {args.objects} objects pushed 2 µm, 16-bit DAC", f"{step_rate:.3g}",
         f"{min(rates):.3g}-{max(rates):.3g}", f">= {STEP_TARGET:.0e}", step_rate >= STEP_TARGET),
        ("the same, 20-bit DAC (the tip moves every sample)", f"{fine_rate:.3g}",
         f"{min(f_rates):.3g}-{max(f_rates):.3g}", f">= {STEP_TARGET:.0e}", fine_rate >= STEP_TARGET),
        (f"full scan {args.pixels}x{args.pixels}, 100 objects, s", f"{scan_s:.3f}",
         f"{min(scans):.3f}-{max(scans):.3f}", f"<= {SCAN_TARGET}", scan_s <= SCAN_TARGET),
        (f"lifted travel samples/s, {args.objects} objects", f"{travel_rate:.3g}",
         f"{min(t_rates):.3g}-{max(t_rates):.3g}", "-", True),
    ]
    cmd = "python bench/bench_world.py" + ("" if argv is None else " " + shlex.join(argv))
    machine = (f"Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.system()}; "
               f"Python {platform.python_version()}, NumPy {np.__version__}")
    workload = (f"Median of {args.runs} runs (fresh random scene per run). Physics: one particle pushed "
                f"2 µm at 200 nm/s, 1 kS/s, one physics step per DAC sample near it (steps per run: "
                f"{', '.join(str(n) for _, n, _ in phys)}; the pushed particle moved "
                f"{', '.join(f'{m:.0f}' for *_, m in phys)} nm: lost from the tip once its path error "
                f"carried it out of the capture cone). At 16 bits the XY code changes every ~7 samples "
                f"at this speed and the samples between cost little; at 20 bits every sample moves the "
                f"tip and the particle.")
    lines = [
        "# Simulated AFM speed", "",
        f"Command: `{cmd}`  ",
        f"Date: {datetime.date.today().isoformat()}  ",
        machine, "", workload, "",
        "| measure | median | (min-max) | target | met |",
        "| --- | ---: | ---: | ---: | :---: |",
        *[f"| {a} | {b} | {c} | {d} | {'yes' if e else 'no'} |" for a, b, c, d, e in rows], "",
    ]
    text = "\n".join(lines)
    Path(args.out).write_text(text)
    print(text)
    return 0 if all(r[-1] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
