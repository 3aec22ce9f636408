"""Golden dry-runs: what the executor does on fixed cases, recorded to compare a refactoring
against (counts, assignment, pushes, instrument time and the final truth to 1e-6 nm).

The cases: the bundled scenes at world and planner seeds 1-3, and each generated family
at seeds 1 and 2, under the full, kalman, anchor, local-scan and open-loop strategies.
Planning budgets are counted in work, so a case gives the same record on any machine
and under any load.

Record them anew (only when a change is meant to change behaviour; say so in the
commit)::

    .venv/bin/python tests/golden_dryruns.py            # all cases, 2 processes
    .venv/bin/python tests/golden_dryruns.py --check    # compare, print the differences
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

GOLDEN = Path(__file__).parent / "golden" / "dryruns.json"
BUNDLED = ("bowtie", "particles", "rods", "mixed")
FAMILIES = ("tiny", "sparse", "dense", "rods", "mixed")
STRATEGIES = ("full", "kalman", "anchor", "local-scan", "open-loop")


def cases() -> list[str]:
    """Case names ``source:name:seed:strategy`` in a fixed order."""
    out = [f"example:{n}:{s}:{st}" for n in BUNDLED for s in (1, 2, 3) for st in STRATEGIES]
    out += [f"family:{n}:{s}:{st}" for n in FAMILIES for s in (1, 2) for st in STRATEGIES]
    return out


def _r(v: float) -> float:
    return round(float(v), 6)


def record(case: str) -> dict:
    """Run one case; the record to compare (JSON types)."""
    from nanoasm.cad.layout import load_layout
    from nanoasm.dryrun import dry_run
    from nanoasm.examples import path as example
    from nanoasm.executor.strategy import ExecOptions
    from nanoasm.planner import PlanOptions
    from nanoasm.world.families import family_case
    from nanoasm.world.scene import load_scene

    source, name, seed, strategy = case.split(":")
    seed = int(seed)
    if source == "example":
        scene, layout = load_scene(example(f"{name}_scene.toml")), load_layout(example(f"{name}.toml"))
    else:
        scene, layout = family_case(name, seed)
    out = dry_run(scene, layout, seed=seed, options=ExecOptions(strategy=strategy),
                  plan_options=PlanOptions(seed=seed))
    rep = out.report
    it = rep.instrument_time
    return {
        "counts": dict(vars(rep.counts)),
        "assignment": [[a.target, a.object] for a in rep.assignment],
        "unfilled": [[u.target, u.reason] for u in rep.unfilled],
        "pushed": list(rep.pushed),
        "failures": [list(f) for f in out.summary.failures],
        "filled": list(out.filled),
        "verdict": [[v.target, v.state] for v in rep.slots],
        "truly_filled": list(out.truly_filled),
        "instrument_time": [_r(it.full_scan), _r(it.local_scan), _r(it.push), _r(it.travel), _r(it.total)],
        "final": {b.id: [_r(b.at[0]), _r(b.at[1]), None if b.angle is None else _r(b.angle)]
                  for b in rep.final_objects},
    }


def _timed(case: str) -> tuple[str, dict, float]:
    t0 = time.perf_counter()
    rec = record(case)
    return case, rec, time.perf_counter() - t0


def differences(case: str, want: dict, got: dict) -> list[str]:
    """Lines naming what differs between two records of ``case`` (none if equal)."""
    out = []
    for key in sorted(set(want) | set(got)):
        if want.get(key) != got.get(key):
            w, g = json.dumps(want.get(key))[:300], json.dumps(got.get(key))[:300]
            out.append(f"{case}: {key}: golden {w} != now {g}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare with the golden file instead of writing it")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--only", default="", help="run only cases containing this text")
    args = ap.parse_args(argv)
    todo = [c for c in cases() if args.only in c]
    golden = json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}
    results: dict[str, dict] = {}
    bad = 0
    with ProcessPoolExecutor(args.workers) as pool:
        for case, rec, secs in pool.map(_timed, todo):
            results[case] = rec
            diff = differences(case, golden.get(case, {}), rec) if args.check else []
            bad += bool(diff)
            print(f"{secs:6.1f} s  {case}  {'DIFFERS' if diff else 'ok'}", flush=True)
            for line in diff:
                print("    " + line)
    if args.check:
        print(f"{len(todo) - bad} equal, {bad} differ")
        return 1 if bad else 0
    golden.update(results)
    GOLDEN.write_text(json.dumps({k: golden[k] for k in sorted(golden)}, indent=1) + "\n")
    print(f"wrote {len(results)} case(s) to {GOLDEN}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
