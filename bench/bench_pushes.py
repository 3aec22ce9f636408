"""Pushes that stay on course, and a report that tells the truth: per push length, how far
from its planned end each pushed object truly came to rest, and per family, whether the
run's own verdict on its slots is what the simulated truth shows.

Dry-runs (strategy ``full``) of the scene families over ten seeds each, every family at
its own drift. For every push, the harness (which alone reads the truth) takes where the
object truly is after it, against where the push was to leave it. Per family: the slots
the truth fills (the largest matching of slots to compatible objects within tolerance,
as an outside scorer counts), their RMS error, collateral moves (objects never pushed
that moved more than the position tolerance), whether the run's verdict equals the
truth, and the instrument time per filled slot. The RMS error is over the slots the
truth fills, each by the object that fills it there (not necessarily the one the run
assigned).

    python bench/bench_pushes.py                      # -> bench/RESULTS_pushes.md
    python bench/bench_pushes.py --families allpushed --seeds 1-3 --out /tmp/x.md
    python bench/bench_pushes.py --between-legs line  # a line across between legs
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from functools import partial

from bench_drift_refs import _fmt, family_sweep, provenance

FAMILIES = ("sparse", "dense", "mixed", "allpushed", "wide", "device")
BINS = ((0.0, 300.0, "< 300 nm"), (300.0, 1000.0, "300-1000 nm"), (1000.0, 2000.0, "1-2 µm"),
        (2000.0, math.inf, "> 2 µm"))


def one_run(args: tuple[str, int], between_legs: str | None = None) -> dict:
    from nanoasm.dryrun import dry_run
    from nanoasm.executor.strategy import ExecOptions
    from nanoasm.world.families import family_case

    name, seed = args
    scene, layout = family_case(name, seed)
    w0 = time.perf_counter()
    legs = {} if between_legs is None else {"between_legs": between_legs}
    out = dry_run(scene, layout, options=ExecOptions(strategy="full", **legs))
    rep = out.report
    tol = layout.tolerance.position
    pushed = set(rep.pushed) | {a.object for a in rep.assignment}
    start = {b.id: b.at for b in rep.initial_objects}
    collateral = [b.id for b in rep.final_objects if b.id in start and b.id not in pushed
                  and math.dist(b.at, start[b.id]) > tol]
    truth_err = truth_errors(layout, rep.final_objects)
    filled = len(out.truly_filled)
    return {"family": name, "seed": seed, "slots": len(layout.targets), "filled": filled,
            "verdict": len(out.verdict_filled), "agrees": not out.disagreements,
            "rms": math.sqrt(sum(e * e for e in truth_err) / len(truth_err)) if truth_err else math.nan,
            "collateral": len(collateral), "instrument_s": rep.instrument_time.total,
            "after_scan_s": rep.instrument_time.total - rep.instrument_time.full_scan,
            "pushes": [(p.planned, p.off) for p in out.pushes], "strokes": rep.counts.pushes,
            "wall_s": time.perf_counter() - w0}


def truth_errors(layout, final) -> list[float]:
    """Centre errors (nm) of the slots the truth fills, each by the object that fills it in
    the outside scorer's matching (:func:`nanoasm.dryrun.truth_slots`), whatever the run
    assigned there."""
    import numpy as np
    from scipy.optimize import linear_sum_assignment

    from nanoasm.planner.assign import in_slot

    targets, final = list(layout.targets), list(final)
    if not targets or not final:
        return []
    ok = np.array([[in_slot(t, o, layout.tolerance) for o in final] for t in targets], dtype=bool)
    dist = np.array([[math.dist(t.at, o.at) for o in final] for t in targets])
    rows, cols = linear_sum_assignment(np.where(ok, dist, 1e9) - 1e12 * ok)
    return [float(dist[i, j]) for i, j in zip(rows, cols) if ok[i, j]]


def report(rows: list[dict], argv: list[str], seconds: float) -> str:
    lines = ["# Pushes that stay on course, and a verdict that tells the truth", "",
             *provenance("bench_pushes.py", argv, len(rows), seconds), "Strategy `full`. Off course: how far from the push's planned end the object truly came to "
             "rest (a push of a particle goes in legs; this is the whole push).", "",
             "## Pushes by planned length (every family)", "",
             "| length | pushes | median off nm | > 50 nm off | > 100 nm off |", "| --- | ---: | ---: | ---: | ---: |"]
    every = [p for r in rows for p in r["pushes"]]
    for lo, hi, name in BINS:
        offs = [off for planned, off in every if lo <= planned < hi]
        if offs:
            lines.append(f"| {name} | {len(offs)} | {statistics.median(offs):.1f} "
                         f"| {100 * sum(o > 50 for o in offs) / len(offs):.1f} % "
                         f"| {100 * sum(o > 100 for o in offs) / len(offs):.1f} % |")
    lines += ["", "## Per family (sums over seeds; RMS and time per slot: medians)", "",
              "| family | runs | slots filled (truth) | verdict = truth | RMS nm | collateral moves | strokes "
              "| s per filled slot after the full scan |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for fam in dict.fromkeys(r["family"] for r in rows):
        rs = [r for r in rows if r["family"] == fam]
        per = [r["after_scan_s"] / r["filled"] for r in rs if r["filled"]]
        rms = [r["rms"] for r in rs if not math.isnan(r["rms"])]
        lines.append(f"| {fam} | {len(rs)} | {sum(r['filled'] for r in rs)}/{sum(r['slots'] for r in rs)} "
                     f"| {sum(r['agrees'] for r in rs)}/{len(rs)} | {_fmt(statistics.median(rms) if rms else math.nan)} "
                     f"| {sum(r['collateral'] for r in rs)} | {sum(r['strokes'] for r in rs)} "
                     f"| {_fmt(statistics.median(per) if per else math.nan)} |")
    lines += ["", "## Every run", "", "| family | seed | filled (truth) | verdict | agrees | RMS nm | collateral "
              "| instrument s | wall s |", "| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r['family']} | {r['seed']} | {r['filled']}/{r['slots']} | {r['verdict']} | "
              f"{'yes' if r['agrees'] else 'NO'} | {_fmt(r['rms'])} | {r['collateral']} | "
              f"{_fmt(r['instrument_s'], 4)} | {_fmt(r['wall_s'])} |" for r in rows]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(add_help=False)
    ap.add_argument("--between-legs", choices=("line", "contact"), default=None,
                    help="how a long push's particle is located between legs (default: ExecOptions')")
    known, rest = ap.parse_known_args(argv)
    return family_sweep(__doc__, FAMILIES, "RESULTS_pushes.md", partial(one_run, between_legs=known.between_legs),
                        report, rest)


if __name__ == "__main__":
    raise SystemExit(main())
