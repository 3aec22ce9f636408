"""Benchmark: simulated full scan and identification of a 512 x 512 image, 100 objects.

Run ``python bench/bench_identify.py [--runs N] [--seed S]``; prints the median wall
time of each step over N runs and how many objects identification found.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np

from nanoasm.bodies import Body
from nanoasm.world.identify import identify
from nanoasm.world.render import make_surface, render_scan

AREA = 10000.0
PIXELS = 512


def scene(rng: np.random.Generator, n: int = 100) -> list[Body]:
    """``n`` objects (one in five a rod) at least 400 nm apart in a 10 µm square."""
    bodies: list[Body] = []
    while len(bodies) < n:
        at = tuple(rng.uniform(600, AREA - 600, 2))
        if any(math.dist(at, b.at) < 400 + (b.length or 0) / 2 for b in bodies):
            continue
        if len(bodies) % 5 == 0:
            d = rng.uniform(30, 100)
            b = Body(f"o{len(bodies)}", "rod", at, d, rng.uniform(0, 180), d * rng.uniform(3, 8))
            if any(math.dist(at, o.at) < 400 + b.length / 2 for o in bodies):
                continue
        else:
            b = Body(f"o{len(bodies)}", "particle", at, rng.uniform(40, 150))
        bodies.append(b)
    return bodies


def median_time(fn, runs: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    bodies = scene(rng)
    surface = make_surface(bodies, [], (AREA, AREA), rng=rng)
    ps = AREA / PIXELS
    t_render, img = median_time(lambda: render_scan(surface, ps, line_offset_prob=0.01,
                                                    line_offset_rms=0.5, rng=rng), args.runs)
    t_ident, env = median_time(lambda: identify(img), args.runs)
    kinds = {k: sum(o.kind == k for o in env.objects) for k in ("particle", "rod", "wire")}
    print(f"scene: {len(bodies)} objects ({sum(b.kind == 'rod' for b in bodies)} rods), "
          f"{PIXELS}x{PIXELS} px at {ps:.2f} nm")
    print(f"render_scan  median {1000 * t_render:7.1f} ms over {args.runs} runs")
    print(f"identify     median {1000 * t_ident:7.1f} ms over {args.runs} runs")
    print(f"found: {kinds}, obstacles {len(env.obstacles)}")


if __name__ == "__main__":
    main()
