"""Speed versus error: the strategies and their knobs on generated scene families.

Dry-runs (``nanoasm.sweep``) of the scene families of ``nanoasm.world.families``
(sparse and dense particles, rods, mixed with electrodes) over seeds:

- every strategy at the default knobs, drift 0.3 nm/s;
- the ``full`` strategy with one knob at a time moved off its default (scan-line length
  factor, reference-scan interval, push speed, rod push step, the drift filter's two
  process noises, the replanning threshold, the planner's budget), to the
  multiples of its default in ``FACTORS``, and the samples per scan line
  (``scan_spacing``, 0.5 and 2 nm between samples);
- every strategy at drift 0.05 and 1 nm/s.

Writes the medians over seeds as tables with the physical bound of each family
(``nanoasm.executor.bound.physical_bound`` of the first plan) and the ratio of the
instrument time to it, a Pareto plot (instrument time per filled slot against RMS slot
error, marker for the fill rate), and every run's row as CSV::

    python bench/speed_vs_error.py                 # the full grid: bench/RESULTS.md, .png, .csv
    python bench/speed_vs_error.py --quick         # a small grid in a minute, into the current folder
    python bench/speed_vs_error.py --scheduler tcp://host:8786    # on a Dask cluster
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shlex
import sys
import time
from pathlib import Path

from nanoasm import sweep as sw
from nanoasm.executor.strategy import STRATEGIES, ExecOptions
from nanoasm.planner.options import PlanOptions
from nanoasm.world.families import DEFAULT_DRIFT

FAMILIES = ("sparse", "dense", "rods", "mixed")
SEEDS = (1, 2, 3)
#: One knob at a time, strategy full: these multiples of its default (ExecOptions / PlanOptions).
FACTORS = {
    "line_factor": (0.5, 2.0),          # scan-line length factor
    "reference_every": (0.25, 5.0),     # s between drift reference scans
    "push_speed": (0.5, 2.0),           # nm/s
    "rod_swing": (0.5, 2.0),            # rod push step, degrees per push
    "drift_q": (0.01, 100.0),           # Kalman process noise on the drift velocity, nm²/s³
    "drift_q_offset": (0.1, 10.0),      # Kalman process noise on the offset, nm²/s
    "replan_after": (0.5, 4.0),         # nm off course before replanning
    "budget": (0.2, 5.0),          # planning work per path (units of ompl_setup)
}
KNOBS = {k: tuple(float(f"{f * getattr(ExecOptions() if k in sw.EXEC_KNOBS else PlanOptions(), k):.6g}")
                  for f in fs) for k, fs in FACTORS.items()}
# the samples per scan line: nm between them (default None, min(1 nm, R/10)), not a multiple
KNOBS["scan_spacing"] = (0.5, 2.0)
DRIFTS = (0.05, 1.0)
QUICK = dict(families=("tiny", "sparse"), seeds=(1,), knobs={k: v[:1] for k, v in KNOBS.items()}, drifts=(1.0,))
STYLE = {"open-loop": "tab:red", "local-scan": "tab:orange", "kalman": "tab:blue", "full": "tab:green",
         "anchor": "tab:purple"}
FILL_MARKERS = ((0.8, "o", "fill >= 0.8"), (0.5, "s", "0.5-0.8"), (0.2, "^", "0.2-0.5"), (0.0, "D", "< 0.2"))


def cases(families, seeds, knobs, drifts) -> list[sw.Case]:
    base = sw.grid(families, seeds, STRATEGIES)
    turned = [c for c in sw.grid(families, seeds, ["full"], knobs=knobs) if c.knobs]
    drifted = sw.grid(families, seeds, STRATEGIES, drifts=drifts)
    return base + turned + drifted


def _f(v, digits: int = 3) -> str:
    if v is None:
        return "-"
    return f"{v:.{digits}g}" if isinstance(v, float) else str(v)


def _table(head: list[str], rows: list[list]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "|".join(" --- " if i < 3 else " ---: " for i in range(len(head))) + "|",
            *["| " + " | ".join(_f(v) for v in r) + " |" for r in rows]]


def pareto(points: list[tuple[float, float, dict]]) -> list[list[dict]]:
    """Points no other point beats in both coordinates (lower is better), by increasing x;
    configurations with the same figures share one entry."""
    front: dict[tuple[float, float], list[dict]] = {}
    for x, y, g in points:
        if not any(x2 <= x and y2 <= y and (x2 < x or y2 < y) for x2, y2, _ in points):
            front.setdefault((x, y), []).append(g)
    return [front[k] for k in sorted(front)]


def _points(groups: list[dict], fam: str, *, filled: bool = True):
    """(RMS assigned, time per filled slot, group) of a family's groups that filled a slot
    (``filled``), or (RMS assigned, total instrument time, group) of those that filled none."""
    return [(g["rms_assigned_nm"], g["per_filled_slot_s"] if filled else g["instrument_s"], g) for g in groups
            if g["family"] == fam and g["rms_assigned_nm"] is not None
            and (g["per_filled_slot_s"] is not None) == filled]


def _name(g: dict) -> str:
    parts = [g["strategy"]]
    if g["knob"] != "default":
        parts.append(g["knob"])
    if g["drift"] != DEFAULT_DRIFT:
        parts.append(f"drift {g['drift']:g}")
    return " ".join(parts)


def plot(groups: list[dict], families, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import ScalarFormatter

    n = len(families)
    cols = 2 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6.2 * cols, 4.8 * rows), squeeze=False)
    for ax, fam in zip(axes.flat, families):
        for filled in (True, False):
            for x, y, g in _points(groups, fam, filled=filled):
                marker = next(m for lo, m, _ in FILL_MARKERS if g["fill_rate"] >= lo) if filled else "x"
                default = g["knob"] == "default" and g["drift"] == DEFAULT_DRIFT
                ax.scatter(x, y, s=70 if default else 28, marker=marker, color=STYLE[g["strategy"]],
                           alpha=1.0 if default else 0.55, linewidths=0.6 if filled else 1.2,
                           edgecolors=("black" if default else "none") if filled else None)
        front = pareto(_points(groups, fam))
        if front:
            ax.plot([f[0]["rms_assigned_nm"] for f in front], [f[0]["per_filled_slot_s"] for f in front],
                    color="black", lw=0.8, ls="--", zorder=0)
            for k, f in enumerate(front, start=1):
                ax.annotate(str(k), (f[0]["rms_assigned_nm"], f[0]["per_filled_slot_s"]), fontsize=7,
                            xytext=(3, 3), textcoords="offset points")
        bound = next((g["bound_s"] for g in groups if g["family"] == fam and g["bound_s"]), None)
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.set_title(f"{fam}: bound {_f(bound)} s (push, scan lines, travel)", fontsize=10)
        ax.set_xlabel("RMS error of the assigned slots, nm")
        ax.set_ylabel("instrument time per filled slot, s")
        ax.grid(True, which="both", lw=0.3, alpha=0.5)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    handles = [Line2D([], [], ls="", marker="o", color=c, label=s) for s, c in STYLE.items()]
    handles += [Line2D([], [], ls="", marker=m, color="grey", label=lab) for _, m, lab in FILL_MARKERS]
    handles += [Line2D([], [], ls="", marker="x", color="grey", label="none filled: at its total time"),
                Line2D([], [], ls="--", color="black", label="Pareto front (numbered as in RESULTS.md)")]
    fig.legend(handles=handles, loc="lower center", ncol=6, fontsize=8, frameon=False)
    fig.suptitle("Speed versus error, medians over seeds. Large outlined markers: each strategy at its defaults, "
                 "drift 0.3 nm/s; small: a knob or the drift moved", fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 0.97))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(rows: list[dict], groups: list[dict], families, args, wall: float, png: Path, csv: Path,
           argv) -> str:
    cmd = "python bench/speed_vs_error.py" + ("" if not argv else " " + shlex.join(argv))
    seeds = sorted({r["seed"] for r in rows})
    errors = [r for r in rows if r["error"]]
    where = f"on {args.scheduler}" if args.scheduler else f"{args.workers or os.cpu_count()} worker process(es)"
    lines = [
        "# Speed versus error", "",
        f"Command: `{cmd}`  ",
        f"Code: {_commit()}  ",
        f"Date: {datetime.date.today().isoformat()}; {len(rows)} dry-runs in {wall / 60:.1f} min wall on {where}; "
        f"{len(errors)} failed  ",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.system()}; "
        f"Python {platform.python_version()}", "",
        f"Scene families of `nanoasm.world.families` ({', '.join(families)}), seeds {', '.join(map(str, seeds))}. "
        "Every figure is a median over the seeds. *fill*: fraction of slots filled (within 20 nm, rods 3°); "
        "*RMS filled*: RMS centre error of the filled slots (the dry-run summary's figure); *RMS assigned*: "
        "of every assigned slot, misses included; *s/slot*: instrument time (full scan included) per "
        "filled slot, over the seeds that filled one; *bound*: `physical_bound` of the first plan (push, "
        "the fewest ch. 5 scan lines, travel; no full scan, no settling, no mode switches); *T/bound*: "
        "instrument time over the bound; *(T-scan)/bound*: the same without the first full scan, "
        "which the bound leaves out (the bound counts the fewest local scans, which open-loop does not "
        "make, so its ratio may fall below 1); *(T-scan)/(bound+sw)*: over the bound with the "
        "instrument's mode switches added, into contact and back once per push of the plan "
        "(`Bound.with_switches_s`). Every row's figures are in "
        f"[{csv.name}]({csv.name}).", "",
        "## Strategies at the default knobs, drift 0.3 nm/s", "",
    ]
    head = ["family", "strategy", "bound s", "fill", "RMS filled nm", "RMS assigned nm", "T s", "s/slot",
            "T/bound", "(T-scan)/bound", "(T-scan)/(bound+sw)"]
    sel = [g for g in groups if g["knob"] == "default" and g["drift"] == DEFAULT_DRIFT]
    lines += _table(head, [[g["family"], g["strategy"], g["bound_s"], g["fill_rate"], g["rms_error_nm"],
                            g["rms_assigned_nm"], g["instrument_s"], g["per_filled_slot_s"], g["ratio"],
                            g["ratio_after_scan"], g["ratio_after_scan_switch"]] for g in sel])
    lines += ["", "## One knob at a time (strategy full, drift 0.3 nm/s)", "",
              "`default` is the full strategy at its defaults, for reference. Knobs: "
              + ", ".join(f"`{k}` {', '.join(_f(v) for v in vals)}" for k, vals in args.knobs.items()) + ".", ""]
    head = ["family", "knob", "fill", "RMS filled nm", "RMS assigned nm", "T s", "s/slot", "(T-scan)/bound",
            "(T-scan)/(bound+sw)"]
    sel = [g for g in groups if g["strategy"] == "full" and g["drift"] == DEFAULT_DRIFT]
    lines += _table(head, [[g["family"], g["knob"], g["fill_rate"], g["rms_error_nm"], g["rms_assigned_nm"],
                            g["instrument_s"], g["per_filled_slot_s"], g["ratio_after_scan"],
                            g["ratio_after_scan_switch"]] for g in sel])
    lines += ["", "## Drift speed by strategy (default knobs)", ""]
    head = ["family", "drift nm/s", "strategy", "fill", "RMS filled nm", "RMS assigned nm", "s/slot"]
    sel = sorted((g for g in groups if g["knob"] == "default"),
                 key=lambda g: (families.index(g["family"]), g["drift"], STRATEGIES.index(g["strategy"])))
    lines += _table(head, [[g["family"], g["drift"], g["strategy"], g["fill_rate"], g["rms_error_nm"],
                            g["rms_assigned_nm"], g["per_filled_slot_s"]] for g in sel])
    lines += ["", "## Pareto front", "", f"![speed versus error]({png.name})", "",
              "Configurations that no other beats in both RMS error of the assigned slots and instrument "
              "time per filled slot (medians; configurations that filled nothing have no time per slot and "
              "are drawn as x at their total time), numbered as on the plot:", ""]
    for fam in families:
        lines.append(f"- **{fam}**: " + "; ".join(
            f"{k}. {' = '.join(_name(g) for g in f)} ({_f(f[0]['rms_assigned_nm'])} nm, "
            f"{_f(f[0]['per_filled_slot_s'])} s/slot, fill {_f(f[0]['fill_rate'])})"
            for k, f in enumerate(pareto(_points(groups, fam)), start=1)))
    if errors:
        lines += ["", "## Failed runs", ""] + [f"- {r['case']}: {r['error']}" for r in errors]
    return "\n".join(lines) + "\n"


def _commit() -> str:
    """The checkout this script ran from: commit and whether files differed from it."""
    import subprocess

    here = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "-C", str(here), "describe", "--always", "--dirty"], capture_output=True,
                             text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "not a git checkout"
    return f"commit {rev}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a small grid (tiny and sparse, one seed)")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes (default: CPU count)")
    ap.add_argument("--scheduler", default=None, help="dask.distributed scheduler address")
    ap.add_argument("--out-dir", type=Path, default=None,
                    help="where RESULTS.md, speed_vs_error.png and .csv go (default: bench/, or . with --quick)")
    args = ap.parse_args(argv)
    grid = QUICK if args.quick else dict(families=FAMILIES, seeds=SEEDS, knobs=KNOBS, drifts=DRIFTS)
    args.knobs = grid["knobs"]
    out = args.out_dir or (Path(".") if args.quick else Path(__file__).resolve().parent)
    out.mkdir(parents=True, exist_ok=True)
    md, png, csv = out / "RESULTS.md", out / "speed_vs_error.png", out / "speed_vs_error.csv"
    todo = cases(grid["families"], grid["seeds"], grid["knobs"], grid["drifts"])
    print(f"{len(todo)} dry-runs", file=sys.stderr)
    t0 = time.perf_counter()

    def progress(done: int, total: int) -> None:
        print(f"\r{done}/{total} ({time.perf_counter() - t0:.0f} s)", end="", file=sys.stderr, flush=True)

    rows = sw.sweep(todo, workers=args.workers, scheduler=args.scheduler, progress=progress)
    wall = time.perf_counter() - t0
    print(file=sys.stderr)
    groups = sw.medians(rows)
    sw.write_table(rows, csv)
    plot(groups, list(grid["families"]), png)
    text = report(rows, groups, list(grid["families"]), args, wall, png, csv, argv if argv is not None else sys.argv[1:])
    md.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
