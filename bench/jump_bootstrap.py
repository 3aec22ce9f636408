"""The drift estimate at the bootstrap's end when the drift jumps 300 nm during the full
scan or just after it: offset error (nm) and velocity error (nm/s) against the simulated
truth, per seed; each run is stopped at its first drift estimate (the bootstrap's), so a
sweep takes minutes where whole runs whose bootstrap went wrong take hours.

    python bench/jump_bootstrap.py mixed 1-10 2        # 2 s after the full scan's end
    python bench/jump_bootstrap.py mixed 1-10 -250     # 250 s before it: a torn scan
    python bench/jump_bootstrap.py scale300 1-10 none  # no jump: is one taken anyway?
    python bench/jump_bootstrap.py scale300 1-10 -1095 # a tear halfway through a 2191 s scan

The full scan takes a second per 10 nm row (mixed: 500 s, allpushed: 600 s). The truth is
read by the dry-run harness's push log (``nanoasm.dryrun._PushLog``, which holds the
simulated world), never by the executor, against the offset at the run's start
(instrument time 0, the layout frame's epoch); the true velocity is the scene's drift
velocity plus its steady change at that time. Also per seed: how many of the objects the
full scan identified are believed more than 50 nm from any true object as the estimate
is made (a tear placed wrongly moves those on the rows between by the jump), read from
the bootstrap's context by wrapping ``drift_bootstrap.emit_drift``. Figures and reading
in ``bench/RESULTS_drift_refs.md``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


class _Stop(Exception):
    pass


def main(argv: list[str]) -> int:
    import nanoasm.dryrun as dryrun
    import nanoasm.executor.drift_bootstrap as drift_bootstrap
    from nanoasm.executor.strategy import ExecOptions
    from nanoasm.world.families import family_case

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_drift_refs import parse_seeds, with_jump

    family, seeds = argv[0], parse_seeds(argv[1])
    after = None if argv[2] == "none" else float(argv[2])
    got: dict = {}
    keep, emit = dryrun._PushLog.__call__, drift_bootstrap.emit_drift

    def first_estimate(self, topic, doc):
        got["sim"] = self.sim
        keep(self, topic, doc)
        d = dryrun.as_dict(doc)
        if topic == "event" and "the drift jumped" in str(d.get("text", "")):
            got["jump"] = d["text"]
        if topic == "drift":
            t = float(d["t"])
            truth = np.asarray(self.sim.true_offset(t)) - np.asarray(self.sim.true_offset(0.0))
            got.update(t=t, offset=np.asarray(d["offset"], float) - truth, velocity=np.asarray(d["velocity"], float))
            raise _Stop

    def objects_off(ctx, t):
        sim, ep = got["sim"], ctx.drift.epoch
        shift = np.asarray(sim.true_offset(ep)) - np.asarray(ctx.drift.origin)
        truth = np.array([np.asarray(b.at) + shift for b in sim.truth()])
        off = [float(np.hypot(*(truth - ctx.position(oid)).T).min()) for oid in ctx.belief.objects]
        got["off"] = (sum(e > 50.0 for e in off), max(off, default=0.0))
        yield from emit(ctx, t)

    dryrun._PushLog.__call__ = first_estimate
    drift_bootstrap.emit_drift = objects_off
    print("| seed | jump at s | estimate at s | offset error nm | velocity error nm/s | jump the bootstrap took "
          "| objects > 50 nm off (worst nm) |")
    print("| ---: | ---: | ---: | ---: | ---: | --- | ---: |")
    for seed in seeds:
        scene, layout = family_case(family, seed)
        if after is not None:
            scene = with_jump(scene, 300.0, after)
        change = scene.params.drift_change
        at = f"{change.jump_at:.0f}" if change.jump else "none"
        got.clear()
        try:
            dryrun.dry_run(scene, layout, options=ExecOptions(strategy="full", trust_after_scan=0.0))
        except _Stop:
            pass
        if "offset" not in got:
            print(f"| {seed} | {at} | - | no estimate | - | - | - |", flush=True)
            continue
        v_true = np.asarray(scene.params.drift.velocity) + np.asarray(change.acceleration) * got["t"]
        took = got.get("jump", "none").split(": taken")[0].replace("the drift jumped by ", "")
        off = f"{got['off'][0]} ({got['off'][1]:.0f})" if "off" in got else "-"    # no estimate by the bootstrap
        print(f"| {seed} | {at} | {got['t']:.0f} | {np.hypot(*got['offset']):.1f} "
              f"| {np.hypot(*(got['velocity'] - v_true)):.3f} | {took} | {off} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
