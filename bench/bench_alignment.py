"""Benchmark: registration of a layout by its marks on rendered scans.

Run ``python bench/bench_alignment.py [--cases N] [--turn DEG] [--scale] [--seed S]``.
Each case renders a 3 x 3 µm scan at 10 nm per pixel (0.3 nm noise) of two electrode
pads and an L marker, 40 nm high, turned by a random angle within ±DEG and shifted by up
to ±300 nm against the layout that draws them axis-aligned, identifies it and registers
the layout (``nanoasm.planner.alignment.register``). Prints the refusals, the largest and
median slot error (where the found transform puts the layout's three slots against where
the true one does), the rotation error, the residual and the time of a registration.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from test_alignment import PADS, layout_doc, scanned  # noqa: E402

from nanoasm.cad.frame import Similarity  # noqa: E402
from nanoasm.cad.layout import layout_from_dict  # noqa: E402
from nanoasm.errors import InputError  # noqa: E402
from nanoasm.planner.alignment import register  # noqa: E402
from nanoasm.world.identify import identify  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--turn", type=float, default=10.0)
    ap.add_argument("--scale", action="store_true", help="register with the scale free")
    ap.add_argument("--seed", type=int, default=12)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    layout = layout_from_dict(layout_doc(Similarity()), "chip.toml")
    errors, turns, residuals, times, refused = [], [], [], [], []
    for k in range(args.cases):
        truth = Similarity(float(rng.uniform(-args.turn, args.turn)), tuple(float(v) for v in rng.uniform(-300, 300, 2)))
        env = identify(scanned([truth.polygon(p) for p in PADS], seed=k))
        t0 = time.perf_counter()
        try:
            a = register(layout, env, scale=args.scale)
        except InputError as err:
            refused.append(f"{truth.line()}: {err.problem}")
            continue
        times.append(time.perf_counter() - t0)
        errors.append(max(math.dist(a.transform.point(t.at), truth.point(t.at)) for t in layout.targets))
        turns.append(abs(a.transform.rotation - truth.rotation))
        residuals.append(a.transform.residual)
    print(f"{args.cases} cases, turns within ±{args.turn:g} deg{', scale free' if args.scale else ''}: "
          f"{len(refused)} refused")
    for line in refused:
        print(f"  refused: {line}")
    if errors:
        print(f"slot error: max {max(errors):.2f} nm, median {statistics.median(errors):.2f} nm; rotation error max "
              f"{max(turns):.3f} deg; residual median {statistics.median(residuals):.1f} nm, max {max(residuals):.1f} "
              f"nm; registration {statistics.median(times) * 1e3:.0f} ms median, {max(times) * 1e3:.0f} ms max")


if __name__ == "__main__":
    main()
