"""Drift references that cannot run out: the drift estimate against the simulated truth,
family by family, over ten seeds each.

Dry-runs (strategy ``full``) of the scene families of :mod:`nanoasm.world.families`,
each at its own drift (sparse, rods and mixed at 0.3 nm/s, dense at 0.6 nm/s; ``device``,
``allpushed``, ``rodgap`` and ``wide`` at a speed drawn per seed in 0.15-0.6 nm/s; every world's creep and drift
acceleration drawn about the filter's nominal values). Per run, from the drift
estimates the run sent and the simulated truth at the same times (the harness reads
the truth; the executor never does):

- the largest σ of the estimate after the bootstrap (worst direction), nm;
- the RMS error of the estimate over the run, nm, and the share of updates whose error
  lies within 3σ (squared Mahalanobis distance at most 11.83, the 2-dof equivalent);
- the instrument time spent on drift references (reference scans and relocalisations)
  as a share of the time after the full scan, and the same with the bootstrap;
- particle slots filled and their RMS error; relocalisations.

Plus the drift-jump case: ``allpushed`` with a 300 nm jump injected 150 s after the
full scan (which takes a second a 10 nm row: 600 s), in the middle of the pushes (the runs
end 1050-1560 s; ``tests/test_repair.py`` jumps at the same 750 s). ``--jump-family`` and
``--jump-after`` move it: ``--families '' --jump-family mixed --jump-after 2`` strikes
as the references are scanned again after the full scan (the bootstrap).

    python bench/bench_drift_refs.py                      # 8 families x 10 seeds -> bench/RESULTS_drift_refs.md
    python bench/bench_drift_refs.py --families device --seeds 1-3 --out /tmp/x.md
    python bench/bench_drift_refs.py --families '' --contact-batch 4,1 --out /tmp/jump.md   # both settings

``--contact-batch`` runs every case with each ``ExecOptions.contact_batch`` it lists
(default: the executor's).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path

FAMILIES = ("sparse", "dense", "rods", "mixed", "device", "allpushed", "rodgap", "wide")
#: 2-dof χ² of probability 0.9973 (the 3σ of one dimension).
CHI2_3SIGMA = 11.829


#: Seconds after the full scan (a second a 10 nm row) at which the jump case's drift jumps.
JUMP_AFTER = 150.0


def with_jump(scene, jump: float, after: float):
    """``scene`` whose drift jumps by ``jump`` nm ``after`` s after its full scan ends (a
    second a 10 nm row; negative: while it is made)."""
    change = replace(scene.params.drift_change, jump=jump, jump_at=scene.area[0] / 10.0 + after)
    return replace(scene, params=replace(scene.params, drift_change=change))


def one_run(args: tuple) -> dict:
    """Dry-run one family and seed (``jump`` nm of drift jump ``after`` s after the full
    scan, :data:`JUMP_AFTER` if not given; 0 nm: none) with ``ExecOptions.trust_after_scan``
    at ``trust`` s and ``contact_batch`` ``batch`` (None if not given: the default)."""
    from nanoasm.dryrun import dry_run
    from nanoasm.executor.strategy import ExecOptions
    from nanoasm.world.families import family_case

    name, seed, jump, trust, after, batch = (*args, JUMP_AFTER, None)[:6]
    scene, layout = family_case(name, seed)
    if jump:
        scene = with_jump(scene, jump, after)
    w0 = time.perf_counter()
    options = ExecOptions(strategy="full", trust_after_scan=trust).batched(batch)
    out = dry_run(scene, layout, options=options)
    wall = time.perf_counter() - w0
    pts = out.drift
    after = pts[1:] if len(pts) > 1 else pts          # the first update is the bootstrap's
    sig = [p.sigma for p in after if p.sigma is not None]
    err = [p.error for p in pts]
    m2 = [p.mahalanobis2 for p in pts if p.mahalanobis2 is not None]
    rep, summ = out.report, out.summary
    t = rep.instrument_time
    after_scan = t.total - t.full_scan
    purposes = getattr(summ, "purposes", None) or {}
    particle = {s.id for s in layout.targets if s.kind == "particle"}
    filled_p = [s for s in out.filled if s in particle]
    errs = [out.errors[s] for s in filled_p]
    return {
        "family": name, "seed": seed, "jump": jump, "updates": len(pts), "batch": options.contact_batch,
        "jump_at": scene.params.drift_change.jump_at if jump else math.nan,
        "max_sigma": max(sig) if sig else math.nan,
        "rms": math.sqrt(sum(e * e for e in err) / len(err)) if err else math.nan,
        "max_err": max(err) if err else math.nan,
        "within3": (sum(v <= CHI2_3SIGMA for v in m2) / len(m2)) if m2 else math.nan,
        "ref_share": (purposes.get("reference", 0.0) + purposes.get("relocalise", 0.0)) / after_scan
        if after_scan > 0 else math.nan,
        "ref_boot_share": sum(purposes.values()) / after_scan if after_scan > 0 else math.nan,
        "relocalise_s": purposes.get("relocalise", 0.0),
        "particle_slots": len(particle), "particle_filled": len(filled_p),
        "particle_true": len([s for s in out.truly_filled if s in particle]),
        "agree": not out.disagreements,
        "particle_rms": math.sqrt(sum(e * e for e in errs) / len(errs)) if errs else math.nan,
        "slots": len(layout.targets), "filled": len(out.filled),
        "pushes": rep.counts.pushes, "instrument_s": t.total, "wall_s": wall,
    }


def code_version(folder: Path) -> str:
    """The commit the benchmark ran at, marked when the tree had uncommitted changes."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], capture_output=True, text=True, cwd=folder).stdout.strip()

    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    return commit + (" with uncommitted changes" if git("status", "--porcelain", "--untracked-files=no") else "")


def parse_seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def _median(rows, key):
    vals = [r[key] for r in rows if not math.isnan(r[key])]
    return statistics.median(vals) if vals else math.nan


def _fmt(v, d=3) -> str:
    """A table cell: ``-`` for None or NaN, ``d`` significant digits for a float."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.{d}g}" if isinstance(v, float) else str(v)


def provenance(script: str, argv: list[str], runs: int, seconds: float) -> list[str]:
    """A results file's command and date lines: the code, the machine and its load."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    return [f"Command: `{shlex.join(['python', f'bench/{script}', *argv])}`  ",
            f"Date: {datetime.date.today()}; code: {code_version(Path(__file__).parent)}; {runs} dry-runs in "
            f"{seconds / 60:.1f} min on {os.cpu_count()} cores ({platform.machine()}, Python "
            f"{platform.python_version()}, load {load:.1f}).", ""]


def family_sweep(doc: str, families, out_name: str, one_run, report, argv: list[str]) -> int:
    """A sweep of ``one_run((family, seed))`` over the command line's families and seeds,
    ``report(rows, argv, seconds)`` written to the results file as it goes."""
    a = sweep_args(doc, families, out_name).parse_args(argv)
    todo = [(f, s) for f in a.families.split(",") for s in parse_seeds(a.seeds)]
    sweep_to_file(todo, one_run, a.workers, Path(a.out),
                  lambda done, secs: report([done[k] for k in range(len(todo)) if k in done], argv, secs))
    return 0


def report(rows: list[dict], jump_rows: list[dict], argv: list[str], seconds: float,
           jump_case: tuple[str, float] = ("allpushed", JUMP_AFTER)) -> str:
    lines = ["# Drift references: the estimate against the simulated truth", "",
             *provenance("bench_drift_refs.py", argv, len(rows) + len(jump_rows), seconds),
             "Strategy `full`. σ: the estimate's standard deviation along its worst direction after the "
             "bootstrap; RMS: the estimate's error against the truth over every update; in 3σ: the share of "
             "updates whose squared Mahalanobis error is at most 11.83; references: instrument time of "
             "reference scans and relocalisations over the time after the full scan (with the bootstrap "
             "in brackets); particle slots: filled (the assigned object within tolerance) over all, and the "
             "RMS of the filled; truly: slots an outside scorer finds filled by the nearest compatible true "
             "object; verdict: runs whose own slot verdict equals that truth.", "",
             "## Per family: medians (worst) over seeds", "",
             "| family | contact batch | runs | max σ nm | RMS nm | worst RMS | in 3σ | worst in 3σ | references "
             "| particle slots | truly | particle RMS nm | all slots | pushes | verdict |",
             "|" + " --- |" + " ---: |" * 14]
    for fam, batch in dict.fromkeys((r["family"], r["batch"]) for r in rows):
        rs = [r for r in rows if r["family"] == fam and r["batch"] == batch]
        ps = sum(r["particle_slots"] for r in rs)
        pf = sum(r["particle_filled"] for r in rs)
        lines.append(
            f"| {fam} | {batch} | {len(rs)} "
            f"| {_fmt(_median(rs, 'max_sigma'))} ({_fmt(max(r['max_sigma'] for r in rs))}) "
            f"| {_fmt(_median(rs, 'rms'))} | {_fmt(max(r['rms'] for r in rs))} "
            f"| {_fmt(_median(rs, 'within3'))} | {_fmt(min(r['within3'] for r in rs))} "
            f"| {_fmt(_median(rs, 'ref_share'))} ({_fmt(_median(rs, 'ref_boot_share'))}) "
            f"| {pf}/{ps} | {sum(r['particle_true'] for r in rs)}/{ps} | {_fmt(_median(rs, 'particle_rms'))} "
            f"| {sum(r['filled'] for r in rs)}/{sum(r['slots'] for r in rs)} | {_fmt(_median(rs, 'pushes'))} "
            f"| {sum(r['agree'] for r in rs)}/{len(rs)} |")
    if jump_rows:
        lines += ["", f"## A 300 nm drift jump {jump_case[1]:g} s after the full scan ({jump_case[0]})", "",
                  "| contact batch | seed | jump at s | run ended s | particle slots | truly | particle RMS nm "
                  "| RMS of estimate nm | relocalisation s | verdict agrees |",
                  "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for batch in dict.fromkeys(r["batch"] for r in jump_rows):
            rs = [r for r in jump_rows if r["batch"] == batch]
            lines.append(f"| {batch} | all {len(rs)} | | median {_fmt(_median(rs, 'instrument_s'), 4)} "
                         f"| {sum(r['particle_filled'] for r in rs)}/{sum(r['particle_slots'] for r in rs)} "
                         f"| {sum(r['particle_true'] for r in rs)} | {_fmt(_median(rs, 'particle_rms'))} "
                         f"| {_fmt(_median(rs, 'rms'))} | {_fmt(_median(rs, 'relocalise_s'))} "
                         f"| {sum(r['agree'] for r in rs)}/{len(rs)} |")
        lines += [f"| {r['batch']} | {r['seed']} | {_fmt(r['jump_at'], 4)} | {_fmt(r['instrument_s'], 4)} "
                  f"| {r['particle_filled']}/{r['particle_slots']} | {r['particle_true']} "
                  f"| {_fmt(r['particle_rms'])} | {_fmt(r['rms'])} | {_fmt(r['relocalise_s'])} "
                  f"| {'yes' if r['agree'] else 'no'} |" for r in jump_rows]
    lines += ["", "## Every run", "",
              "| family | contact batch | seed | updates | max σ | RMS | max err | in 3σ | references "
              "| with bootstrap | particle | particle RMS | slots | pushes | instrument s | wall s |",
              "|" + " --- |" + " ---: |" * 15]
    lines += [f"| {r['family']} | {r['batch']} | {r['seed']} | {r['updates']} "
              f"| {_fmt(r['max_sigma'])} | {_fmt(r['rms'])} "
              f"| {_fmt(r['max_err'])} | {_fmt(r['within3'])} | {_fmt(r['ref_share'])} | {_fmt(r['ref_boot_share'])} "
              f"| {r['particle_filled']}/{r['particle_slots']} | {_fmt(r['particle_rms'])} "
              f"| {r['filled']}/{r['slots']} | {r['pushes']} | {_fmt(r['instrument_s'], 4)} | {_fmt(r['wall_s'])} |"
              for r in rows]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = sweep_args(__doc__, FAMILIES, "RESULTS_drift_refs.md")
    ap.add_argument("--jump-seeds", default="1-10", help="seeds of the drift-jump case ('' for none)")
    ap.add_argument("--jump-family", default="allpushed", help="family of the drift-jump case")
    ap.add_argument("--jump-after", type=float, default=JUMP_AFTER,
                    help=f"s after the full scan's end at which the jump case's drift jumps (default {JUMP_AFTER:g})")
    ap.add_argument("--trust-after-scan", type=float, default=0.0,
                    help="ExecOptions.trust_after_scan of every run, s (default 0, the executor's)")
    ap.add_argument("--contact-batch", default="",
                    help="ExecOptions.contact_batch: every case with each of these (comma-separated; default "
                         "the executor's)")
    a = ap.parse_args(argv)
    seeds = parse_seeds(a.seeds)
    batches = [int(b) for b in a.contact_batch.split(",") if b] or [None]
    cases = [(f, s, 0.0, a.trust_after_scan, JUMP_AFTER, b) for b in batches for f in a.families.split(",") if f
             for s in seeds]
    jumps = ([(a.jump_family, s, 300.0, a.trust_after_scan, a.jump_after, b) for b in batches
              for s in parse_seeds(a.jump_seeds)] if a.jump_seeds else [])
    todo = cases + jumps
    sweep_to_file(todo, one_run, a.workers, Path(a.out),
                  lambda done, secs: report([done[k] for k in range(len(cases)) if k in done],
                                            [done[k] for k in range(len(cases), len(todo)) if k in done],
                                            argv, secs, (a.jump_family, a.jump_after)))
    return 0


def sweep_args(doc: str, families, out_name: str) -> argparse.ArgumentParser:
    """The options every family sweep of this folder takes: families, seeds, workers and
    the results file (beside the script)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--families", default=",".join(families))
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=str(Path(__file__).with_name(out_name)))
    return ap


def sweep_to_file(todo: list, fn, workers: int, out: Path, render) -> None:
    """Run ``fn`` on every case of ``todo`` in worker processes; after every finished run,
    ``render(done: index -> row, seconds)`` is written to ``out`` (atomically; a long
    sweep stopped loses nothing, and a partial file says how many of how many)."""
    t0, done = time.perf_counter(), {}
    text = ""
    with ProcessPoolExecutor(workers) as pool:
        futures = {pool.submit(fn, c): k for k, c in enumerate(todo)}
        for fut in as_completed(futures):
            done[futures[fut]] = fut.result()
            text = render(done, time.perf_counter() - t0)
            if len(done) < len(todo):
                text += f"\n(partial: {len(done)} of {len(todo)} runs)\n"
            tmp = out.with_suffix(".tmp")
            tmp.write_text(text)
            tmp.replace(out)
            print(f"{len(done)}/{len(todo)} {todo[futures[fut]]}", flush=True)
    print(text)


if __name__ == "__main__":
    raise SystemExit(main())
