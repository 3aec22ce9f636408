"""The simulated world a dry-run keeps beside its log, for resuming.

A real run's world goes on by itself; a dry-run's lives in this process. So the dry-run
harness keeps it beside the log (``run.mcap.sim``), replaced atomically at every
checkpoint, and a run killed at any moment leaves a world that matches one of the log's
checkpoints (:func:`nanoasm.executor.resume.resume_point` picks that one). The world is a
pickle: only open files you wrote.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np

from nanoasm.errors import InputError
from nanoasm.executor.documents import CHECKPOINT, as_dict
from nanoasm.fileio import write_atomic

SIM_SUFFIX = ".sim"
SIM_FORMAT = "nanoasm.simstate/1"


def sim_state_path(log_path: str | os.PathLike) -> Path:
    """Where a dry-run keeps its simulated world beside ``log_path``."""
    p = Path(log_path)
    return p.with_name(p.name + SIM_SUFFIX)


class SimKeeper:
    """Dry-run harness subscriber: after every checkpoint, the simulated world (pickled)
    and what the report needs from before the run, written atomically to ``path``."""

    def __init__(self, path: str | os.PathLike, sim, extra: dict):
        self.path, self.sim, self.extra = Path(path), sim, extra

    def __call__(self, topic: str, doc) -> None:
        if topic != CHECKPOINT:
            return
        t = float(as_dict(doc).get("t", self.sim.clock()))
        blob = pickle.dumps({"format": SIM_FORMAT, "t": t, "sim": self.sim, **self.extra},
                            protocol=pickle.HIGHEST_PROTOCOL)
        write_atomic(self.path, blob, mode=0o600)     # a pickle: for its owner alone


def load_sim_state(path: str | os.PathLike, state: dict | None = None) -> dict:
    """The simulated world kept beside a dry-run's log (``t``: its instrument time); if
    ``state`` is given it must be that checkpoint's. Only open files you wrote: they are
    pickles."""
    p = Path(path)
    if not p.is_file():
        raise InputError(str(path), None, "the simulated world of this dry-run is missing (it is "
                                          "written beside the log as LOG.sim)")
    try:
        kept = pickle.loads(p.read_bytes())
    except Exception as err:          # a damaged file: say so in one line
        raise InputError(str(path), None, f"unreadable simulated world ({type(err).__name__})") from None
    if not isinstance(kept, dict) or kept.get("format") != SIM_FORMAT:
        raise InputError(str(path), None, "not a nanoasm simulated world")
    if state is not None and not np.isclose(float(kept["t"]), float(state["t"]), rtol=0.0, atol=1e-6):
        raise InputError(str(path), None, f"holds the world at t = {kept['t']:.3f} s, but the log's last "
                                          f"checkpoint is at t = {float(state['t']):.3f} s")
    return kept
