"""Rods that arrive (issue 14): rod slots, their errors, pushes and instrument time per rod,
and the executor's pivot offset estimates against the simulated world's.

Dry-runs (strategy ``full``) of the rod families of :mod:`nanoasm.world.families`, ten
seeds each. Per run, from the report and the simulated truth (read by the harness and
this script; the executor never does):

- rod slots filled, as an outside scorer counts them (nearest compatible true object
  within the layout's tolerance), and the centre and angle error of every assigned rod;
- pushes of rods and instrument time per rod slot after the full scan;
- for every rod pushed, the pivot offset the run ended with (``/push``'s ``pivot``)
  against the one the simulated world drew for it, in fractions of its length, signed
  along the executor's axis direction, and how many pushes it folded in.

    python bench/bench_rods.py                       # rods x 10 seeds -> bench/RESULTS_rods.md
    python bench/bench_rods.py --families rods --seeds 1-3 --out /tmp/x.md
"""

from __future__ import annotations

import math
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_drift_refs import _fmt, family_sweep, provenance  # noqa: E402

FAMILIES = ("rods",)


def one_run(args: tuple[str, int]) -> dict:
    """Dry-run one family and seed; the rod figures of the module docstring."""
    from nanoasm.dryrun import dry_run, exec_options
    from nanoasm.executor.documents import as_dict
    from nanoasm.world.families import family_case
    from nanoasm.world.sim.afm import SimulatedAFM

    name, seed = args
    scene, layout = family_case(name, seed)
    pivots: dict[str, dict] = {}
    first_angle: dict[str, float] = {}         # the filter's axis angle after a rod's first push
    surprise: list[float] = []                 # expected vs scanned centre after a rod's 4th+ push
    rod_work: dict[str, list] = {}             # per rod pushed: [pushes, instrument time]
    last_t = None                              # the end of the push before (the first push's
    #                                            time from the full scan's end is not counted)

    def sub(topic, doc):
        nonlocal last_t
        if topic == "push":
            d = as_dict(doc)
            t_prev, last_t = last_t, float(d["t"])
            if d["belief"].get("kind") == "rod":
                work = rod_work.setdefault(d["op"]["object"], [0, 0.0])
                work[0] += 1
                work[1] += last_t - t_prev if t_prev is not None else 0.0
            if d.get("pivot") is not None:
                pivots[d["op"]["object"]] = d["pivot"]
                first_angle.setdefault(d["op"]["object"], d["pivot"]["angle"])
                if d["verdict"] == "pushing" and d["pivot"]["pushes"] > 3:
                    surprise.append(math.dist(d["op"]["expect"]["at"], d["belief"]["at"]))

    out = dry_run(scene, layout, options=exec_options(scene), subscribers=[sub])
    rep = out.report
    table = SimulatedAFM(scene, seed=scene.seed if scene.seed is not None else 0)._world.table
    truth_offset = {b.id: float(table.pivot_offset[i]) for i, b in enumerate(table.bodies)}
    final = {o.id: o for o in rep.final_objects}
    rod_slots = [t for t in layout.targets if t.kind == "rod"]
    assigned = {a.target: a.object for a in rep.assignment}          # scene ids, as final_objects
    centre, angle = [], []
    for t in rod_slots:
        o = final.get(assigned.get(t.id, ""))
        if o is not None and o.angle is not None:
            centre.append(math.dist(t.at, o.at))
            angle.append(abs(math.remainder(o.angle - t.angle, 180.0)))
    # the world's δ is along its rod's own angle, the scene's at the start (a report gives
    # angles modulo 180); one push turns a rod by 20° at most, so the filter's angle after
    # the first push says which way round the two are
    scene_angle = {o.id: o.angle for o in scene.objects if o.angle is not None}
    deltas = []
    for oid, p in pivots.items():
        true_id = out.ids.get(oid)
        if true_id in truth_offset and true_id in scene_angle:
            sign = 1.0 if math.cos(math.radians(first_angle[oid] - scene_angle[true_id])) > 0 else -1.0
            deltas.append((p["offset"], sign * truth_offset[true_id], p["std"], int(p["pushes"])))
    t = rep.instrument_time
    return {"family": name, "seed": seed, "rod_slots": len(rod_slots),
            "rod_true": len([s for s in out.truly_filled if s in {r.id for r in rod_slots}]),
            "centre": centre, "angle": angle, "deltas": deltas, "pushes": rep.counts.pushes,
            "after_scan_s": t.total - t.full_scan, "agree": not out.disagreements,
            "slots": len(layout.targets), "filled": len(out.truly_filled), "surprise": surprise,
            "rod_pushes": [n for n, _ in rod_work.values()], "rod_time": sum(w for _, w in rod_work.values())}


def _pct(v, q: float) -> float:
    return float(np.percentile(v, q)) if v else math.nan


def _median(v) -> float:
    return float(statistics.median(v)) if v else math.nan


def _rms(v) -> float:
    return math.sqrt(sum(x * x for x in v) / len(v)) if v else math.nan


def report(rows: list[dict], argv: list[str], seconds: float) -> str:
    lines = ["# Rods: slots, errors, pushes and the pivot offset estimates", "",
             *provenance("bench_rods.py", argv, len(rows), seconds),
             "Rod slots truly filled (outside scorer); centre and angle RMS of assigned rods; pushes per "
             "run; instrument time after the full scan; δ: the rods' pivot offset estimates at the end "
             "against the world's, fractions of L (|error| ≤ 0.01 among rods with ≥ 6 pushes); after "
             "push: the distance between where a rod was expected after its 4th and later pushes and "
             "where its scan found it, nm, median (90th percentile); pushes per rod: pushes of each rod "
             "pushed, median over the family's rods; rod s per rod slot: instrument time from the end "
             "of the push before to the end of each rod push (travel, scans, drift references, the "
             "push; a run's first push from the end of the push before only), summed over the family and "
             "divided by its rod slots.", "",
             "| family | runs | rod slots | centre RMS nm | angle RMS ° | pushes (median) | time after scan s "
             "(median) | pushes per rod | rod s per rod slot | δ error RMS | within 0.01 (≥ 6 pushes) "
             "| after push nm | verdict agrees |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for fam in dict.fromkeys(r["family"] for r in rows):
        rs = [r for r in rows if r["family"] == fam]
        d = [x for r in rs for x in r["deltas"]]
        d6 = [x for x in d if x[3] >= 6]
        sur = [x for r in rs for x in r.get("surprise", [])]
        lines.append(
            f"| {fam} | {len(rs)} | {sum(r['rod_true'] for r in rs)}/{sum(r['rod_slots'] for r in rs)} "
            f"| {_fmt(_rms([c for r in rs for c in r['centre']]))} | {_fmt(_rms([a for r in rs for a in r['angle']]))} "
            f"| {_fmt(statistics.median(r['pushes'] for r in rs))} "
            f"| {_fmt(statistics.median(r['after_scan_s'] for r in rs), 4)} "
            f"| {_fmt(_median([n for r in rs for n in r['rod_pushes']]))} "
            f"| {_fmt(sum(r['rod_time'] for r in rs) / max(sum(r['rod_slots'] for r in rs), 1), 4)} "
            f"| {_fmt(_rms([a - b for a, b, _, _ in d]))} "
            f"| {sum(abs(a - b) <= 0.01 for a, b, _, _ in d6)}/{len(d6)} "
            f"| {_fmt(_pct(sur, 50))} ({_fmt(_pct(sur, 90))}) "
            f"| {sum(r['agree'] for r in rs)}/{len(rs)} |")
    lines += ["", "## Every run", "",
              "| family | seed | rod slots | all slots | pushes | time after scan s "
              "| δ estimate / truth (± 1σ, pushes) |",
              "| --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    lines += [f"| {r['family']} | {r['seed']} | {r['rod_true']}/{r['rod_slots']} | {r['filled']}/{r['slots']} "
              f"| {r['pushes']} | {_fmt(r['after_scan_s'], 4)} | "
              + ", ".join(f"{a:+.3f}/{b:+.3f} (±{s:.3f}, {n})" for a, b, s, n in r["deltas"]) + " |"
              for r in rows]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    return family_sweep(__doc__, FAMILIES, "RESULTS_rods.md", one_run, report,
                        sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    raise SystemExit(main())
