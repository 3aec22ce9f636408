"""Resuming a stopped run from its log: the last checkpoint and what the run was given.

A run log holds a ``/checkpoint`` after every push: the executor's whole state
(:func:`~nanoasm.executor.checkpoints.checkpoint`, read back as a
:class:`~nanoasm.executor.documents.CheckpointDoc`). ``nanoasm run --resume`` and
``nanoasm dry-run --resume`` read the last one and go on from there
(:meth:`~nanoasm.executor.assembly.Assembly.resume`), writing a new log beside the old
one. What else a harness needs to go on is its own business (a dry-run keeps its
world beside the log).
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
class ResumePoint:
    """What a log offers for resuming: the last checkpoint's state (with the identified
    environment and the first plan, ``env`` and ``first_plan``) and the run's inputs."""

    path: str
    state: dict
    layout: Any                          # cad.layout.Layout
    metadata: dict[str, str]             # the log's "nanoasm" metadata record
    scene: Any = None                    # world.scene.Scene (dry-runs)


#: What resumes each kind of run log.
RESUMED_BY = {"dry-run": "nanoasm dry-run --resume", "run": "nanoasm run --resume"}


def resume_point(path: str | os.PathLike, kind: str, at: float | None = None) -> ResumePoint:
    """Read ``path`` (the log of a ``kind`` run, "dry-run" or "run", complete or cut short)
    for resuming from its last checkpoint, or from the one at instrument time ``at`` (a
    dry-run's kept world may be one checkpoint behind the log, if the run was killed
    between the two writes). InputError naming the file and the problem when it cannot be
    resumed."""
    from nanoasm.cad.layout import layout_from_dict
    from nanoasm.executor.logread import read_log
    from nanoasm.world.scene import scene_from_dict

    p = Path(path)
    if not p.is_file():
        raise InputError(str(path), None, "no such run log")
    log = read_log(p, topics={CHANNELS[t] for t in (CHECKPOINT, RESULT, ENVIRONMENT, PLAN)})
    if not log.channels and not log.attachments:
        raise InputError(str(path), None, f"not a readable run log ({log.problem or 'no records'})")
    logged = log.metadata.get("nanoasm", {}).get("kind")
    if logged != kind:
        other = RESUMED_BY.get(logged or "", "")
        raise InputError(str(path), None, f"not a {kind}'s log" + (f" (resume it with {other})" if other else ""))
    if log.last(CHANNELS[RESULT]) is not None:
        raise InputError(str(path), None, "the run finished; there is nothing to resume")
    ckpts = [doc for _, doc in log.documents(CHECKPOINT)]
    if at is not None:
        ckpts = [c for c in ckpts if abs(c.t - at) <= 1e-6]
    ckpt = ckpts[-1] if ckpts else None
    if ckpt is None and at is not None:
        raise InputError(str(path), CHANNELS[CHECKPOINT], f"no checkpoint at t = {at:.3f} s, where the kept "
                                                          "simulated world stands")
    if ckpt is None:
        raise InputError(str(path), CHANNELS[CHECKPOINT], "the log has no checkpoint (the run stopped before "
                                                          "its first push ended); start it again")
    layout_doc = log.attachment_json("layout.json")
    if layout_doc is None:
        raise InputError(str(path), "layout.json", "the log has no layout attached")
    layout = layout_from_dict(layout_doc, f"{path}: layout.json")
    scene_doc = log.attachment_json("scene.json")
    scene = scene_from_dict(scene_doc, f"{path}: scene.json") if scene_doc is not None else None
    env, plan = log.documents(ENVIRONMENT), log.documents(PLAN)
    if not env or not plan:
        raise InputError(str(path), CHANNELS[ENVIRONMENT if not env else PLAN],
                         "the log lacks what the run identified or planned first")
    scan = log.attachments.get(FULL_SCAN_ATTACHMENT)
    try:
        image = full_scan_image(scan) if scan is not None else None
    except ValueError as err:
        raise InputError(str(path), FULL_SCAN_ATTACHMENT, str(err)) from None
    state = {**ckpt.to_dict(), "env": env[0][1].to_dict(), "first_plan": plan[0][1].to_dict(),
             "full_scan": image}
    return ResumePoint(str(path), state, layout, dict(log.metadata.get("nanoasm", {})), scene)


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
