"""Sweeps: many seeded dry-runs in parallel, locally or on a Dask cluster, as one table.

A :class:`Case` is a generated scene family (:mod:`nanoasm.world.families`), a seed, a
strategy, a drift speed and knobs (fields of
:class:`~nanoasm.executor.strategy.ExecOptions` or
:class:`~nanoasm.planner.options.PlanOptions`, by name). :func:`run_case` dry-runs one
and gives a row; :func:`sweep` runs a list of them in batches on a
``ProcessPoolExecutor`` (or in this process with one worker) or, given a scheduler
address, on ``dask.distributed`` workers, which need nanoasm installed; rows come back
in the order of the cases, identical whichever way they ran, but for ``wall_s``.

Every row (see :data:`COLUMNS`): the case, fill rate, RMS slot error (of the filled
slots, as the dry-run summary gives it, and of every assigned slot), instrument time
in total and per filled slot, the physical lower bound of the first plan
(:func:`~nanoasm.executor.bound.physical_bound`) and the ratio of the instrument time to
it, with and without the first full scan (which the bound leaves out), counts and wall
time. A case that raises is a row with its ``error`` and the sweep goes on.
"""

from __future__ import annotations

import csv
import io
import math
import os
import signal
import statistics
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, fields
from multiprocessing import get_context
from pathlib import Path

from nanoasm.errors import InputError
from nanoasm.executor.strategy import STRATEGIES, ExecOptions
from nanoasm.fileio import dumps_json, write_atomic
from nanoasm.planner.options import PlanOptions
from nanoasm.world.families import DEFAULT_DRIFT, FAMILIES, family

#: Knobs a case may set: ExecOptions and PlanOptions fields (the strategy and the
#: planner's seed are set by the case itself).
EXEC_KNOBS = tuple(f.name for f in fields(ExecOptions) if f.name != "strategy")
PLAN_KNOBS = tuple(f.name for f in fields(PlanOptions) if f.name != "seed")
KNOBS = EXEC_KNOBS + PLAN_KNOBS

COLUMNS = ("case", "family", "seed", "strategy", "drift", "knob", "slots", "filled", "fill_rate",
           "rms_error_nm", "rms_assigned_nm", "instrument_s", "full_scan_s", "per_filled_slot_s",
           "bound_s", "ratio", "ratio_after_scan", "bound_switch_s", "ratio_after_scan_switch", "pushes",
           "failed_pushes", "local_scans", "replans",
           "wall_s", "error")
#: Most cases in one batch. Tasks of milliseconds want batches of ~50 (LIBRARIES.md),
#: but a dry-run takes 0.1-20 s, so a few per batch make dispatch negligible while
#: progress stays fine-grained and a Ctrl-C drops little finished work.
MAX_BATCH = 8

Progress = Callable[[int, int], None]


def knob_value(name: str, text: str):
    """``text`` as a value of knob ``name``, typed like the knob's default."""
    if name not in KNOBS:
        raise ValueError(f"unknown knob {name!r}; one of {', '.join(KNOBS)}")
    default = getattr(ExecOptions() if name in EXEC_KNOBS else PlanOptions(), name)
    if isinstance(default, str):
        return text
    try:
        value = int(text) if isinstance(default, int) else float(text)
    except ValueError:
        kind = "an integer" if isinstance(default, int) else "a number"
        raise ValueError(f"knob {name} must be {kind}, got {text!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"knob {name} must be finite, got {text!r}")
    return value


def parse_names(text: str, valid: Sequence[str], what: str) -> list[str]:
    """A comma list of names from ``valid`` (``all`` for every one)."""
    names = list(valid) if text.strip() == "all" else [n.strip() for n in text.split(",") if n.strip()]
    for n in names:
        if n not in valid:
            raise ValueError(f"unknown {what} {n!r}; one of {', '.join(valid)} (or all)")
    if not names:
        raise ValueError(f"no {what} given")
    return names


def parse_families(text: str) -> list[str]:
    """Scene families as a comma list: the named families (``all`` for every one) and
    ``scaleN``, N objects at a constant density (:func:`~nanoasm.world.families.scale_family`)."""
    names = list(FAMILIES) if text.strip() == "all" else [n.strip() for n in text.split(",") if n.strip()]
    for n in names:
        family(n)
    if not names:
        raise ValueError("no family given")
    return names


def parse_seeds(text: str) -> list[int]:
    """Seeds as a comma list of numbers and ranges: ``1-5``, ``1,4,9``, ``1-3,10``."""
    seeds: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        lo, dash, hi = part.partition("-")
        try:
            a, b = int(lo), int(hi if dash else lo)
        except ValueError:
            raise ValueError(f"seeds are numbers and ranges such as 1-5 or 1,4,9, got {text!r}") from None
        if a < 0 or b < a:
            raise ValueError(f"a seed range runs from a seed >= 0 up, got {part!r}")
        seeds += [s for s in range(a, b + 1) if s not in seeds]
    return seeds


def parse_numbers(text: str, what: str) -> list[float]:
    """A comma list of finite numbers >= 0."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"{what} must be numbers separated by commas, got {text!r}") from None
    if not all(math.isfinite(v) and v >= 0 for v in values):
        raise ValueError(f"{what} must be finite and >= 0, got {text!r}")
    return values


def parse_knob(text: str) -> tuple[str, list]:
    """``NAME=V1,V2,...`` as the knob's name and its typed values."""
    name, eq, values = text.partition("=")
    if not eq or not values:
        raise ValueError(f"a knob is NAME=V1,V2,..., got {text!r}")
    return name.strip(), [knob_value(name.strip(), v.strip()) for v in values.split(",")]


@dataclass(frozen=True)
class Case:
    """One dry-run of a sweep. ``knobs``: ``(name, value)`` pairs, at most one per name."""

    family: str
    seed: int
    strategy: str = "full"
    drift: float = DEFAULT_DRIFT
    knobs: tuple[tuple[str, object], ...] = ()

    def __post_init__(self) -> None:
        family(self.family)
        if self.strategy not in STRATEGIES:
            raise ValueError(f"unknown strategy {self.strategy!r}; one of {', '.join(STRATEGIES)}")
        if self.seed < 0:
            raise ValueError(f"seed must not be negative, got {self.seed}")
        names = [k for k, _ in self.knobs]
        for name in names:
            if name not in KNOBS:
                raise ValueError(f"unknown knob {name!r}; one of {', '.join(KNOBS)}")
        if len(set(names)) != len(names):
            raise ValueError(f"a knob is given twice: {', '.join(names)}")
        self.options()           # the values are checked where the options are made

    @property
    def knob(self) -> str:
        return ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.knobs) or "default"

    @property
    def label(self) -> str:
        return f"{self.family}/seed={self.seed}/{self.strategy}/drift={self.drift:g}/{self.knob}"

    def options(self) -> tuple[ExecOptions, PlanOptions]:
        knobs = dict(self.knobs)
        ex = ExecOptions(strategy=self.strategy, **{k: v for k, v in knobs.items() if k in EXEC_KNOBS})
        plan = PlanOptions(seed=self.seed, **{k: v for k, v in knobs.items() if k in PLAN_KNOBS})
        return ex, plan


def grid(families: Sequence[str], seeds: Iterable[int], strategies: Sequence[str] = ("full",), *,
         drifts: Sequence[float] = (DEFAULT_DRIFT,), knobs: dict[str, Sequence] | None = None) -> list[Case]:
    """Cases of every family x drift x strategy x seed at the default knobs, and for each
    knob value in ``knobs`` the same with that one knob changed (one knob at a time)."""
    variants: list[tuple[tuple[str, object], ...]] = [()]
    for name, values in (knobs or {}).items():
        variants += [((name, v),) for v in values]
    seeds = list(seeds)
    return [Case(f, s, st, d, kv) for f in families for d in drifts for kv in variants
            for st in strategies for s in seeds]


def _rounded(x: float | None, digits: int = 3) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x, digits)


def run_case(case: Case) -> dict:
    """Dry-run ``case``; its row (see :data:`COLUMNS`). An exception becomes ``error``."""
    from nanoasm.dryrun import dry_run
    from nanoasm.executor.bound import physical_bound
    from nanoasm.world.families import family_case

    row: dict = dict.fromkeys(COLUMNS)
    row.update(case=case.label, family=case.family, seed=case.seed, strategy=case.strategy,
               drift=case.drift, knob=case.knob)
    t0 = time.perf_counter()
    try:
        scene, layout = family_case(case.family, case.seed, case.drift)
        options, plan_options = case.options()
        out = dry_run(scene, layout, seed=case.seed, options=options, plan_options=plan_options)
        rep, t = out.report, out.report.instrument_time
        b = physical_bound(out.summary.plan, options, scene.params.scanner, objects=out.summary.env,
                           timing=scene.params.timing, tip_radius=plan_options.tip_radius)
        bound, with_switches = b.total_s, b.with_switches_s
        n, filled = len(layout.targets), len(out.filled)
        errors = list(out.errors.values())
        rms_assigned = math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else None
        row.update(
            slots=n, filled=filled, fill_rate=round(filled / n, 4), rms_error_nm=_rounded(out.rms_error),
            rms_assigned_nm=_rounded(rms_assigned),
            instrument_s=round(t.total, 3), full_scan_s=round(t.full_scan, 3),
            per_filled_slot_s=round(t.total / filled, 3) if filled else None,
            bound_s=round(bound, 3), ratio=_rounded(t.total / bound) if bound > 0 else None,
            ratio_after_scan=_rounded((t.total - t.full_scan) / bound) if bound > 0 else None,
            bound_switch_s=round(with_switches, 3),
            ratio_after_scan_switch=_rounded((t.total - t.full_scan) / with_switches) if with_switches > 0 else None,
            pushes=rep.counts.pushes, failed_pushes=rep.counts.failed_pushes,
            local_scans=rep.counts.local_scans, replans=rep.counts.replans)
    except Exception as exc:           # noqa: BLE001 - recorded in the row, the sweep goes on
        row["error"] = f"{type(exc).__name__}: {exc}"
    row["wall_s"] = round(time.perf_counter() - t0, 3)
    return row


def run_batch(batch: Sequence[tuple[int, Case]]) -> list[tuple[int, dict]]:
    """Rows of a batch of ``(index, case)``, keeping the indices."""
    return [(i, run_case(c)) for i, c in batch]


def batches(cases: Sequence[Case], workers: int) -> list[list[tuple[int, Case]]]:
    """Indexed cases in batches: at least four per worker, at most :data:`MAX_BATCH` cases each."""
    size = max(1, min(MAX_BATCH, len(cases) // (4 * max(workers, 1))))
    indexed = list(enumerate(cases))
    return [indexed[k:k + size] for k in range(0, len(indexed), size)]


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a sweep: ``rows`` holds the rows of the cases that had finished."""

    def __init__(self, rows: list[dict], total: int):
        super().__init__(f"interrupted after {len(rows)} of {total} case(s)")
        self.rows, self.total = rows, total


def _ignore_sigint() -> None:
    # Ctrl-C reaches the whole process group: the parent alone stops the sweep
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def sweep(cases: Sequence[Case], *, workers: int | None = None, scheduler: str | None = None,
          progress: Progress | None = None) -> list[dict]:
    """Run ``cases`` and return their rows in case order.

    Parameters
    ----------
    cases : sequence of Case
    workers : int, optional
        Local worker processes (default: the CPU count); 1 runs in this process. Ignored
        with ``scheduler``.
    scheduler : str, optional
        Address of a dask.distributed scheduler (``tcp://host:8786``): the batches run
        on its workers.
    progress : callable(done, total), optional
        Called as cases finish.

    Raises
    ------
    Interrupted
        On Ctrl-C, after the workers are stopped, with the rows finished so far.
    InputError
        When the scheduler cannot be reached or dask.distributed is not installed.
    """
    workers = workers or os.cpu_count() or 1
    done: dict[int, dict] = {}

    def collect(pairs) -> None:
        done.update(pairs)
        if progress is not None:
            progress(len(done), len(cases))

    try:
        if scheduler is not None:
            _on_dask(scheduler, batches(cases, workers), collect)
        elif workers == 1:
            for b in batches(cases, 1):
                collect(run_batch(b))
        else:
            _on_processes(batches(cases, workers), workers, collect)
    except KeyboardInterrupt:
        raise Interrupted([done[i] for i in sorted(done)], len(cases)) from None
    return [done[i] for i in range(len(cases))]


def _on_processes(work: list, workers: int, collect) -> None:
    pool = ProcessPoolExecutor(max_workers=min(workers, len(work)) or 1, mp_context=get_context("spawn"),
                               initializer=_ignore_sigint)
    try:
        pending = {pool.submit(run_batch, b) for b in work}
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                collect(fut.result())
    except BaseException:
        # stop now: queued batches are dropped, running ones killed (a batch takes minutes)
        procs = list((getattr(pool, "_processes", None) or {}).values())
        for proc in procs:
            proc.kill()
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown()


def _on_dask(address: str, work: list, collect) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise InputError(None, "--scheduler", "needs dask.distributed: pip install 'nanoasm[sweep]'") from None
    try:
        client = Client(address, timeout="10s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(None, "--scheduler", f"cannot reach {address}: {exc}") from None
    futures = []
    try:
        futures = [client.submit(run_batch, b, pure=False) for b in work]
        for fut in as_completed(futures):
            collect(fut.result())
    except BaseException:
        client.cancel(futures)
        raise
    finally:
        client.close()


# -- tables -----------------------------------------------------------------------------

def table_text(rows: Sequence[dict], suffix: str) -> str:
    """Rows as CSV (``.csv``) or a JSON array (``.json``); empty cells for missing values."""
    if suffix == ".json":
        return dumps_json([{c: r.get(c) for c in COLUMNS} for r in rows]) + "\n"
    buf = io.StringIO()
    writer = csv.DictWriter(buf, COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows({c: r.get(c) for c in COLUMNS} for r in rows)
    return buf.getvalue()


def write_table(rows: Sequence[dict], path: str | os.PathLike) -> None:
    """Write the rows to ``path`` (.csv or .json), atomically."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".csv", ".json"):
        raise InputError(str(path), None, "a sweep table must end in .csv or .json")
    write_atomic(path, table_text(rows, suffix))


def _median(values) -> float | None:
    vals = [v for v in values if v is not None]
    return statistics.median(vals) if vals else None


MEDIANS = ("fill_rate", "rms_error_nm", "rms_assigned_nm", "instrument_s", "per_filled_slot_s", "bound_s",
           "ratio", "ratio_after_scan", "ratio_after_scan_switch", "wall_s")


def medians(rows: Sequence[dict], by: Sequence[str] = ("family", "drift", "strategy", "knob")) -> list[dict]:
    """One row per group of ``by``: the number of runs, errors, and the medians over the
    seeds of :data:`MEDIANS` (cases with nothing filled have no RMS error and no time per
    filled slot, so those medians are over the others)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in by), []).append(r)
    out = []
    for key, rs in groups.items():
        ok = [r for r in rs if r["error"] is None]
        out.append({**dict(zip(by, key)), "runs": len(rs), "errors": len(rs) - len(ok),
                    **{m: _median(r[m] for r in ok) for m in MEDIANS}})
    return out
