"""Planner benchmarks: wall time against N, path quality, rods, OMPL planners side by side.

    python bench/bench_planner.py            # writes bench/RESULTS_planner.md

Scenes: N random particles (60-120 nm) at constant density (one per 0.5 um^2) with a few
obstacles; a layout of N/2 particle slots on a grid in the middle. Medians of several
seeds; the machine is shared and noisy, so the figures are indicative, ratios measured
in the same run are the reliable part.
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import time
from datetime import date
from pathlib import Path

from nanoasm.bodies import Body
from nanoasm.cad.layout import Keepout, Layout, Tolerance
from nanoasm.planner import PlanOptions, check_plan, plan_assembly
from nanoasm.world.environment import EnvObject, EnvObstacle, Environment
from nanoasm.world.random_scene import SceneSpec, random_scene


def scene(n: int, seed: int, rods: int = 0, obstacles: int | None = None, targets: int | None = None):
    side = math.sqrt(n * 0.5e6)
    side = max(side, 4000.0)
    n_obst = max(1, n // 50) if obstacles is None else obstacles
    sc = random_scene(SceneSpec(area=(side, side), particles=n, rods=rods, obstacles=n_obst,
                                obstacle_size=(200.0, 600.0), rod_length=(500.0, 900.0)), seed)
    env = Environment(sc.area, tuple(EnvObject(o.id, o.kind, o.at, o.diameter, o.angle, o.length)
                                     for o in sc.objects),
                      tuple(EnvObstacle(ob.polygon, ob.height) for ob in sc.obstacles))
    m = n // 2 if targets is None else targets
    cols = max(1, math.ceil(math.sqrt(m)))
    pitch = 250.0
    x0 = side / 2 - pitch * cols / 2
    tg = []
    for k in range(m):
        tg.append(Body(f"t{k}", "particle", (x0 + pitch * (k % cols), x0 + pitch * (k // cols)), 90.0))
    for k in range(rods):
        tg.append(Body(f"r{k}", "rod", (side / 2 + 600.0 * (k - rods / 2), x0 - 700.0), 80.0, 0.0, 700.0))
    # keep slots clear of the obstacles: drop the ones that overlap
    layout = Layout((side, side), tuple(tg), (), Tolerance(position=20, angle=3, size=0.5), f"grid{m}")
    return layout, env


def run_scaling(sizes, seeds):
    rows = []
    for n in sizes:
        times, ratios, turns, filled = [], [], [], []
        for seed in seeds:
            layout, env = scene(n, seed)
            t0 = time.perf_counter()
            plan, stats = plan_assembly(layout, env, PlanOptions(seed=seed))
            times.append(time.perf_counter() - t0)
            ratios.append(stats.path_ratio)
            turns.append(sum(stats.particle_turns) / max(len(stats.particle_turns), 1))
            filled.append(len(plan.assignment) / len(layout.targets))
        rows.append((n, statistics.median(times), statistics.median(times) / n * 1000,
                     statistics.median(ratios), statistics.median(turns), statistics.median(filled)))
        print(f"N={n}: {rows[-1][1]:.3f} s, {rows[-1][2]:.2f} ms/object", file=sys.stderr)
    return rows


def run_rods(seeds):
    pushes, times, fills = [], [], []
    for seed in seeds:
        layout, env = scene(60, seed, rods=3, targets=10)
        t0 = time.perf_counter()
        plan, stats = plan_assembly(layout, env, PlanOptions(seed=seed))
        times.append(time.perf_counter() - t0)
        pushes += stats.rod_pushes
        rod_slots = [t for t in layout.targets if t.kind == "rod"]
        fills.append(sum(a.target.startswith("r") for a in plan.assignment) / len(rod_slots))
        assert check_plan(plan, layout, env) == []
    return statistics.median(pushes) if pushes else float("nan"), max(pushes, default=0), \
        statistics.median(times), statistics.mean(fills)


def maze(seed: int):
    """A particle behind staggered walls: a straight line never works, OMPL must plan."""
    walls = []
    for k in range(4):
        x = 1500.0 + 1000.0 * k
        y0, y1 = (600.0, 5600.0) if k % 2 == 0 else (0.0, 5000.0)   # gaps alternate: below, above
        walls.append(((x, y0), (x + 150.0, y0), (x + 150.0, y1), (x, y1)))
    layout = Layout((7000.0, 5600.0), (Body("goal", "particle", (6300.0, 2800.0), 100.0),),
                    tuple(Keepout(w) for w in walls), Tolerance(), "maze")
    env = Environment((7000.0, 5600.0), (EnvObject("o1", "particle", (600.0, 300.0 + 50 * seed), 100.0),))
    return layout, env


def run_planners(planners, seeds, budget):
    rows = []
    for name in planners:
        times, ratios, segs, ok = [], [], [], 0
        for seed in seeds:
            layout, env = maze(seed)
            t0 = time.perf_counter()
            plan, stats = plan_assembly(layout, env, PlanOptions(planner=name, budget=budget, seed=seed))
            times.append(time.perf_counter() - t0)
            if not plan.unfilled:
                ok += 1
                ratios.append(stats.path_ratio)
                segs.append(len(plan.operations))
                assert check_plan(plan, layout, env) == []
        rows.append((name, statistics.median(times), statistics.median(ratios) if ratios else float("nan"),
                     statistics.median(segs) if segs else float("nan"), ok, len(seeds)))
        print(f"{name}: {rows[-1][1]:.3f} s", file=sys.stderr)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--budget", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=Path(__file__).with_name("RESULTS_planner.md"))
    args = ap.parse_args()
    seeds = list(range(args.seeds))
    scaling = run_scaling(args.sizes, seeds)
    rod_med, rod_max, rod_time, rod_fill = run_rods(seeds)
    planners = run_planners(["rrtconnect", "rrt", "kpiece", "bkpiece", "prm", "rrtstar", "bitstar",
                             "prmstar", "fmt"], seeds, args.budget)
    lines = [
        "# Planner benchmark", "",
        f"Command: `python bench/bench_planner.py --seeds {args.seeds}` "
        f"({date.today()}, {platform.machine()}, 2 shared cores; medians over {args.seeds} seeds).", "",
        "## Wall time against N (particles at constant density, N/2 slots, obstacles)", "",
        "| N objects | plan wall time (s) | ms per object | path / straight length | turns per object | slots assigned |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
        *[f"| {n} | {t:.3f} | {per:.2f} | {r:.3f} | {tu:.2f} | {f:.0%} |" for n, t, per, r, tu, f in scaling],
        "", "Target: at most 20 ms per object at N = 1000.", "",
        "## Rods (3 rods among 60 particles, zigzag under the pivot model)", "",
        f"Pushes per rod: median {rod_med:.0f}, max {rod_max}; plan wall time median {rod_time:.2f} s; "
        f"rod slots filled {rod_fill:.0%}.", "",
        "## OMPL planners side by side (a particle through four staggered walls)", "",
        f"Budget {args.budget:g} unit(s) of work per path; optimising planners use all of it.", "",
        "| planner | wall time (s) | path / straight length | pushes | solved |",
        "| --- | ---: | ---: | ---: | ---: |",
        *[f"| {n} | {t:.3f} | {r:.3f} | {s:.0f} | {ok}/{tot} |" for n, t, r, s, ok, tot in planners],
        "",
    ]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
