"""Resuming a stopped run from its log: the last checkpoint and what the run was given.

A run log holds a ``/checkpoint`` after every push: the executor's whole state
(:func:`~nanoasm.executor.checkpoints.checkpoint`, read back as a
:class:`~nanoasm.executor.documents.CheckpointDoc`). ``nanoasm run --resume`` and
``nanoasm dry-run --resume`` read the last one and go on from there
(:meth:`~nanoasm.executor.assembly.Assembly.resume`), writing a new log beside the old
one. The new log starts with what a resume takes from the old one (:class:`Inherited`:
the full scan, the first environment and plan, the checkpoint it goes on from), so that
a resumed run killed in turn is resumed from its own log alone. What else a harness
needs to go on is its own business (a dry-run keeps its world beside the log).

A damaged part of a log is skipped (:func:`~nanoasm.executor.logread.read_log`), and the
run goes on from the last checkpoint that reads: every checkpoint holds the whole state,
so one lost in the damage costs nothing when a later one is whole. When the damage took
the last ones, the run goes on from an earlier checkpoint while the sample is as the
later pushes left it: it knows nothing of them, and re-scans each object before pushing
it as always (:attr:`ResumePoint.behind` tells the harness so).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from nanoasm.errors import InputError

from .documents import CHANNELS, CHECKPOINT, ENVIRONMENT, PLAN, RESULT
from .scan_attachment import FULL_SCAN_ATTACHMENT, full_scan_image


@dataclass(frozen=True)
class Inherited:
    """What a resumed run's log carries over from the stopped run's (written by
    :meth:`~nanoasm.executor.runlog.RunLog.carry`): the first ``/environment`` and
    ``/plan`` and the ``/checkpoint`` it goes on from, each ``(t, document)``, and the
    full scan's attachment as logged (None: the log had none)."""

    environment: tuple[float, dict]
    plan: tuple[float, dict]
    checkpoint: tuple[float, dict]
    full_scan: bytes | None = None


@dataclass(frozen=True)
class ResumePoint:
    """What a log offers for resuming: the checkpoint's state (with the identified
    environment and the first plan, ``env`` and ``first_plan``), the run's inputs, what
    the resumed run's log carries over (``inherited``) and the warnings to show: a
    damaged part skipped, a checkpoint that may not be the run's last (``behind``)."""

    path: str
    state: dict
    layout: Any                          # cad.layout.Layout
    metadata: dict[str, str]             # the log's "nanoasm" metadata record
    scene: Any = None                    # world.scene.Scene (dry-runs)
    inherited: Inherited | None = None
    warnings: tuple[str, ...] = ()
    behind: bool = False                 # damage after the checkpoint may have held later ones


#: What resumes each kind of run log.
RESUMED_BY = {"dry-run": "nanoasm dry-run --resume", "run": "nanoasm run --resume"}


def resume_point(path: str | os.PathLike, kind: str, at: float | None = None) -> ResumePoint:
    """Read ``path`` (the log of a ``kind`` run, "dry-run" or "run", complete, cut short or
    damaged) for resuming from its last checkpoint that reads, or from the one at
    instrument time ``at`` (a dry-run's kept world may be one checkpoint behind the log, if
    the run was killed between the two writes; if that checkpoint was lost in a damaged
    part, from the last one before it, :attr:`ResumePoint.behind`). InputError naming the
    file and the problem when it cannot be resumed."""
    from nanoasm.cad.layout import layout_from_dict
    from nanoasm.executor.logread import read_log
    from nanoasm.world.scene import scene_from_dict

    p = Path(path)
    if not p.is_file():
        raise InputError(str(path), None, "no such run log")
    log = read_log(p, topics={CHANNELS[t] for t in (CHECKPOINT, RESULT, ENVIRONMENT, PLAN)})
    if not log.channels and not log.attachments:
        raise InputError(str(path), None, f"not a readable run log ({log.problem or 'no records'})")
    meta = dict(log.metadata.get("nanoasm", {}))
    logged = meta.get("kind")
    if logged != kind:
        other = RESUMED_BY.get(logged or "", "")
        raise InputError(str(path), None, f"not a {kind}'s log" + (f" (resume it with {other})" if other else ""))
    if log.last(CHANNELS[RESULT]) is not None:
        raise InputError(str(path), None, "the run finished; there is nothing to resume")
    ckpt, behind = _checkpoint(log, at)
    layout_doc = log.attachment_json("layout.json")
    if layout_doc is None:
        raise InputError(str(path), "layout.json", "the log has no layout attached")
    layout = layout_from_dict(layout_doc, f"{path}: layout.json")
    scene_doc = log.attachment_json("scene.json")
    scene = scene_from_dict(scene_doc, f"{path}: scene.json") if scene_doc is not None else None
    inherited = _inherited(log, ckpt, meta)
    try:
        image = full_scan_image(inherited.full_scan) if inherited.full_scan is not None else None
    except ValueError as err:
        raise InputError(str(path), FULL_SCAN_ATTACHMENT, str(err)) from None
    state = {**ckpt.to_dict(), "env": inherited.environment[1], "first_plan": inherited.plan[1],
             "full_scan": image}
    warnings = [*log.warnings(), *([_behind(log.path, ckpt, at)] if behind else [])]
    return ResumePoint(str(path), state, layout, meta, scene, inherited, tuple(warnings), behind)


def _checkpoint(log, at: float | None):
    """The checkpoint to go on from (the last that reads, or the one at ``at``) and
    whether a damaged part after it may have held later ones."""
    ckpts = [doc for _, doc in log.documents(CHECKPOINT)]
    if not ckpts:
        raise InputError(log.path, CHANNELS[CHECKPOINT], "the log has no checkpoint (the run stopped before "
                                                         "its first push ended); start it again")
    if at is None:
        ckpt = ckpts[-1]
        return ckpt, any(d.after is not None and d.after >= ckpt.t for d in log.damage)
    there = [c for c in ckpts if abs(c.t - at) <= 1e-6]
    if there:
        return there[-1], False
    before = [c for c in ckpts if c.t < at]
    if not before or not any(_holds(d, at) for d in log.damage):
        raise InputError(log.path, CHANNELS[CHECKPOINT], f"no checkpoint at t = {at:.3f} s, where the kept "
                                                         "simulated world stands")
    return before[-1], True


def _holds(damage, t: float) -> bool:
    """Whether a damaged part may have held what was logged at instrument time ``t``."""
    return ((damage.after is None or damage.after <= t + 1e-6)
            and (damage.before is None or damage.before >= t - 1e-6))


def _behind(path: str, ckpt, at: float | None) -> str:
    """The warning for a run going on from a checkpoint that may not be its last."""
    pushes = ckpt.to_dict().get("counts", {}).get("pushes", "?")
    where = (f"the checkpoint at t = {at:.3f} s, where the kept simulated world stands, was lost in the damage"
             if at is not None else "later checkpoints may have been lost in the damage")
    return (f"{path}: {where}; going on from the one at t = {ckpt.t:.3f} s (after push {pushes}) with the "
            "sample as the later pushes left it, which the run does not know: it scans every object before "
            "pushing it, as always")


def _inherited(log, ckpt, meta: dict[str, str]) -> Inherited:
    """What the run identified and planned first, and the full scan, as a resumed log
    carries them over; InputError when the log lacks them."""
    env, plan = log.documents(ENVIRONMENT), log.documents(PLAN)
    if not env or not plan:
        older = (f" (resumed from {meta['resumed_from']} by a nanoasm that did not carry them over: resume that "
                 "log again)" if meta.get("resumed_from") else "")
        raise InputError(log.path, CHANNELS[ENVIRONMENT if not env else PLAN],
                         "the log lacks what the run identified or planned first" + older)
    return Inherited((log.topic(CHANNELS[ENVIRONMENT])[0].t, env[0][1].to_dict()),
                     (log.topic(CHANNELS[PLAN])[0].t, plan[0][1].to_dict()), (ckpt.t, ckpt.to_dict()),
                     log.attachments.get(FULL_SCAN_ATTACHMENT))


def resumed_log_path(log_path: str | os.PathLike) -> Path:
    """A new log beside ``log_path`` for the resumed run: ``run-resumed.mcap``, then
    ``run-resumed2.mcap``, ... (the stopped run's log is never overwritten)."""
    p = Path(log_path)
    stem = p.stem
    for k in range(1, 1000):
        q = p.with_name(f"{stem}-resumed{'' if k == 1 else k}{p.suffix}")
        if not q.exists():
            return q
    raise InputError(str(log_path), None, "too many resumed logs beside it")


class ShiftedClock:
    """An instrument whose clock goes on from a stopped run's: ``clock() + shift`` and
    signal times shifted alike (a restarted process starts its clock at 0, while the
    drift filter's times must go on increasing)."""

    def __init__(self, instrument, shift: float):
        self._inst, self.shift = instrument, float(shift)
        self.config = instrument.config

    def clock(self) -> float:
        return self._inst.clock() + self.shift

    def write(self, chunk):
        block = self._inst.write(chunk)
        return replace(block, t=np.asarray(block.t) + self.shift)

    def __getattr__(self, name):          # the rest of the Instrument protocol, unchanged
        return getattr(self._inst, name)


def clock_shift(state: dict, now: float) -> float:
    """Shift that puts an instrument clock reading ``now`` after the checkpoint's time by
    the wall-clock time since the checkpoint was saved."""
    gap = max(time.time() - float(state.get("saved_at", time.time())), 0.0)
    return float(state["t"]) + gap - now
