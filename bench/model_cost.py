"""Model only what a scene needs, measured: what a rod and idle objects cost a push.

- **physics per push** (simulated AFM, wall time of the contact part of one 500 nm push
  at 200 nm/s): a particle-only scene (the ``sparse`` family, seed 1), the same scene
  with one rod added away from the push (the rod model is loaded but idle), and a push
  of that rod near its end (the rod model at work);
- **idle objects**: the same particle push in a 40 x 40 µm sample among 0 to 5000 idle
  particles (none within 1 µm of the push);
- **dry-runs** (``full`` strategy): the ``sparse`` family, seeds 1-3, against the same
  scenes with one rod added that no slot wants: wall time of identification, planning
  and execution per push.

Medians of ``--runs`` runs::

    python bench/model_cost.py                 # writes bench/RESULTS_model_cost.md
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

from nanoasm.bodies import Body
from nanoasm.dryrun import dry_run
from nanoasm.executor.strategy import ExecOptions
from nanoasm.instrument import ramp
from nanoasm.world.cantilever import tip_offset
from nanoasm.world.families import family_case
from nanoasm.world.random_scene import SceneSpec, random_scene
from nanoasm.world.scene import Scene
from nanoasm.world.sim import SimulatedAFM, lever_from_params

ROD = dict(kind="rod", diameter=70.0, angle=30.0, length=600.0)


def push_wall(scene: Scene, start, end, seed: int = 1) -> tuple[float, int]:
    """Wall seconds of the contact part of a push from ``start`` to ``end`` (sample frame,
    nm; the tip lands there, the preload's deflection compensated), and physics steps."""
    sim = SimulatedAFM(scene, seed=seed, placement=(0.0, 0.0))
    cfg, p = sim.config, sim.params
    off = tip_offset(cfg.preload / p.cantilever.K_n, 0.0, cfg.scan_angle, lever_from_params(p))[:2]
    (x0, y0), (x1, y1) = np.asarray(start, float) - off, np.asarray(end, float) - off
    points = [(x0, y0, cfg.lift), (x0, y0, -cfg.preload), (x1, y1, -cfg.preload), (x1, y1, cfg.lift)]
    codes, cur = [], sim.position()
    for i, q in enumerate(points):
        c = cfg.nm_to_codes(np.asarray(q, float))
        codes.append(ramp(cur, c, cfg, speed=p.timing.push_speed if i == 2 else None))
        cur = c
    sim.write(codes[0])
    steps = sim.diagnostics()["steps"]
    t = time.perf_counter()
    sim.write(np.vstack(codes[1:3]))
    wall = time.perf_counter() - t
    sim.write(codes[3])
    return wall, sim.diagnostics()["steps"] - steps


def _free_spot(scene: Scene, body: Body) -> Body:
    """``body`` moved along the diagonal until it keeps 300 nm from everything."""
    for k in range(200):
        b = dataclasses.replace(body, at=(body.at[0] + 37.0 * k, body.at[1] + 23.0 * k))
        if all(b.geometry().distance(o.geometry()) > b.radius + o.radius + 300.0 for o in scene.objects):
            return b
    raise RuntimeError("no room for the rod")


def with_rod(scene: Scene) -> tuple[Scene, Body]:
    rod = _free_spot(scene, Body("extra_rod", at=(500.0, 500.0), **ROD))
    return dataclasses.replace(scene, objects=(*scene.objects, rod)), rod


def _particle_push(scene: Scene) -> tuple[tuple[float, float], tuple[float, float]]:
    """A push of the particle nearest the scene's middle, 500 nm along +x past contact."""
    mid = (scene.area[0] / 2, scene.area[1] / 2)
    o = min((b for b in scene.objects if b.kind == "particle"),
            key=lambda b: (b.at[0] - mid[0]) ** 2 + (b.at[1] - mid[1]) ** 2)
    x, y = o.at
    return (x - o.radius - 60.0, y), (x + 500.0, y)


def _rod_push(rod: Body) -> tuple[tuple[float, float], tuple[float, float]]:
    """Across the rod at 10 % of its length from one end, 300 nm past its axis."""
    (ax, ay), (bx, by) = rod.core()
    px, py = ax + 0.1 * (bx - ax), ay + 0.1 * (by - ay)
    c, s = np.cos(np.radians(rod.angle)), np.sin(np.radians(rod.angle))
    nx, ny = -s, c
    return (px - 120.0 * nx, py - 120.0 * ny), (px + 300.0 * nx, py + 300.0 * ny)


def idle_scene(n_idle: int, seed: int) -> Scene:
    side = 40000.0
    base = random_scene(SceneSpec(area=(side, side), particles=n_idle, gap=100.0), seed) if n_idle else \
        Scene((side, side), seed=seed)
    keep = tuple(b for b in base.objects if np.hypot(b.at[0] - side / 2, b.at[1] - side / 2) > 1000.0)
    return dataclasses.replace(base, objects=(*keep, Body("pushed", "particle", (side / 2, side / 2), 90.0)))


def _median_push(scene, start, end, runs) -> tuple[float, int]:
    walls, steps = zip(*(push_wall(scene, start, end, seed=r + 1) for r in range(runs)))
    return statistics.median(walls), int(statistics.median(steps))


def physics_rows(runs: int) -> list[tuple]:
    scene, _ = family_case("sparse", 1)
    start, end = _particle_push(scene)
    rodded, rod = with_rod(scene)
    rows = []
    for label, sc, (a, b) in (("particles only (12 particles), a particle pushed", scene, (start, end)),
                              ("the same + 1 idle rod, the same particle pushed", rodded, (start, end)),
                              ("the same + 1 rod, the rod pushed near an end", rodded, _rod_push(rod))):
        wall, steps = _median_push(sc, a, b, runs)
        rows.append((label, wall * 1e3, steps, wall / max(steps, 1) * 1e6))
    return rows


def idle_rows(runs: int, counts=(0, 100, 1000, 5000)) -> list[tuple]:
    rows = []
    for n in counts:
        scene = idle_scene(n, 7)
        start, end = _particle_push(dataclasses.replace(scene, objects=scene.objects[-1:]))
        wall, steps = _median_push(scene, start, end, runs)
        rows.append((f"{len(scene.objects) - 1} idle particles", wall * 1e3, steps, wall / max(steps, 1) * 1e6))
    return rows


def dry_rows(seeds=(1, 2, 3)) -> list[tuple]:
    out = {"particles only": [], "+ 1 idle rod": []}
    for seed in seeds:
        scene, layout = family_case("sparse", seed)
        for label, sc in (("particles only", scene), ("+ 1 idle rod", with_rod(scene)[0])):
            o = dry_run(sc, layout, seed=seed, options=ExecOptions(strategy="full"))
            w, n = o.report.wall_time, max(o.report.counts.pushes, 1)
            out[label].append((w.identify, w.plan, w.execute / n, o.report.counts.pushes, w.total))
    return [(label, *(statistics.median(v[i] for v in vals) for i in range(5))) for label, vals in out.items()]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--out", default=str(Path(__file__).with_name("RESULTS_model_cost.md")))
    args = ap.parse_args(argv)
    phys, idle, dry = physics_rows(args.runs), idle_rows(args.runs), dry_rows()
    cmd = "python bench/model_cost.py" + ("" if not argv else " " + shlex.join(argv))
    push_table = ["| scene and push | wall ms per push | physics steps | µs per step |", "| --- | ---: | ---: | ---: |",
                  *[f"| {a} | {b:.1f} | {c} | {d:.1f} |" for a, b, c, d in phys + idle]]
    dry_table = ["| sparse family, seeds 1-3 | identify s | plan s | execute s per push | pushes | total s |",
                 "| --- | ---: | ---: | ---: | ---: | ---: |",
                 *[f"| {a} | {b:.3f} | {c:.3f} | {d:.4f} | {e:g} | {f:.2f} |" for a, b, c, d, e, f in dry]]
    lines = ["# Model only what a scene needs", "",
             f"Command: `{cmd}`  ", f"Date: {datetime.date.today().isoformat()}  ",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.system()}; "
             f"Python {platform.python_version()}, NumPy {np.__version__}", "",
             f"Simulated AFM, medians of {args.runs} runs (seeds 1-{args.runs}); a push is 500 nm past contact "
             "at 200 nm/s, 1 kS/s, 16-bit DAC; only its contact part is timed. A physics step is one DAC "
             "sample played through the pushing physics near an object.", "", *push_table, "",
             "Dry-runs (strategy full, medians over seeds; the rod is 600 x 70 nm, 300 nm clear of "
             "everything, and no slot wants it):", "", *dry_table, ""]
    text = "\n".join(lines)
    Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
