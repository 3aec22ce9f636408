"""What a ``scaleN`` dry-run spent its time on: counts of its warning events beside the
slots the truth fills and its own verdict, one JSON row a seed.

The counts: references gated out as moved on their own, relocalisations begun and
failed, pushes that slipped (all, and by kind: :func:`_slips`), objects not found where
believed; ``edge``: slots the verdict calls filled at a measured error beyond 0.6 of the
tolerance (``course.tight``, :mod:`nanoasm.executor.edge_slots`); ``rms`` and ``worst``: the centre errors
(nm) of the slots the truth fills (:func:`bench_pushes.truth_errors`). Used to compare two
trees on the same seeds (run it once from each)::

    python bench/scale_events.py 300 1-3
"""

from __future__ import annotations

import argparse
import json
import math
import re
import time

from bench_pushes import truth_errors

#: Row key -> the text its events contain.
EVENTS = {"moved_on_own": "moved on its own", "relocalising": "relocalising the drift",
          "reloc_failed": "relocalisation failed", "slipped": "slipped", "not_found": "not found"}


def one(n: int, seed: int) -> dict:
    from nanoasm.dryrun import dry_run
    from nanoasm.executor.strategy import ExecOptions
    from nanoasm.planner import PlanOptions
    from nanoasm.world.families import family_case

    scene, layout = family_case(f"scale{n}", seed)
    texts: list[str] = []

    def keep(topic, doc):
        if topic == "event":
            texts.append(doc.text if hasattr(doc, "text") else doc["text"])

    t = time.perf_counter()
    out = dry_run(scene, layout, seed=seed, options=ExecOptions(strategy="full"),
                  plan_options=PlanOptions(seed=seed), subscribers=[keep])
    row = {k: sum(v in x for x in texts) for k, v in EVENTS.items()}
    row.update(_slips(texts))
    from nanoasm.executor.course import tight

    near = tight(layout).position            # beyond it, a filled slot is at its edge
    truth = truth_errors(layout, out.report.final_objects)
    row.update(n=n, seed=seed, truly_filled=len(out.truly_filled), verdict=len(out.verdict_filled),
               disagree=len(out.disagreements),
               edge=sum(v.state == "filled" and v.error is not None and v.error > near
                        for v in out.report.slots),
               rms=round(math.sqrt(sum(e * e for e in truth) / len(truth)), 2) if truth else None,
               worst=round(max(truth), 1) if truth else None, pushes=out.report.counts.pushes,
               instrument_s=round(out.report.instrument_time.total, 1), wall_s=round(time.perf_counter() - t, 1))
    return row


def _slips(texts: list[str]) -> dict:
    """The slips by kind: the push monitor's (a force signature), and pushes the scans
    found had left their particle where it was (``slipped_over``); of these, how many
    were tracked legs stopped on their contact angle within :data:`EARLY` nm, and of
    those how many a line across then found within :data:`ON_LINE` nm of their line."""
    over = [i for i, x in enumerate(texts) if "left it where it was" in x]
    early = on_line = 0
    for i in over:
        oid = texts[i].split()[2]
        legs = [x for x in texts[:i] if x.startswith(oid + ": leg")]
        m = re.search(r"stopped short after (\d+) nm", legs[-1]) if legs else None
        if m and float(m.group(1)) <= EARLY:
            early += 1
            across = re.search(r"([-+][\d.]+) nm off its line \(by a line across\)", legs[-1])
            on_line += bool(across and abs(float(across.group(1))) <= ON_LINE)
    return {"monitor_slips": sum(bool(re.match(r"push of \S+ slipped \(peak", x)) for x in texts),
            "slipped_over": len(over), "stopped_early": early, "stopped_early_on_line": on_line}


#: A tracked leg stopped within this (nm) is stopped at its contact's onset.
EARLY = 40.0
#: A particle a line across finds within this (nm) of its line was not sliding off the tip.
ON_LINE = 4.0


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("n", type=int, help="objects (the scaleN family)")
    ap.add_argument("seeds", help="seeds, e.g. 1-3")
    args = ap.parse_args()
    for seed in _seeds(args.seeds):
        print(json.dumps(one(args.n, seed)), flush=True)


if __name__ == "__main__":
    main()
