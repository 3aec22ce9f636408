"""The simulated world a dry-run keeps beside its log, for resuming.

A real run's world goes on by itself; a dry-run's lives in this process. So the dry-run
harness keeps it beside the log (``run.mcap.sim``), replaced atomically at every
checkpoint, and a run killed at any moment leaves a world that matches one of the log's
checkpoints (:func:`nanoasm.executor.resume.resume_point` picks that one).

The file is JSON (``nanoasm.simstate/2``): the checkpoint's time, the instrument clock at
the start, the true objects at the start, and the world's state
(:meth:`~nanoasm.world.sim.SimulatedAFM.state_dict`: parameters, seed, objects, clock,
tip, drift, random generators' states). It is data, never code: reading it parses JSON
(:func:`read_sim_state`, at most :data:`MAX_SIM_BYTES`), and the world is built from the
log's scene only after every field was checked and the state found to be of that scene
(:func:`restore_sim`). A bad file is one line naming it.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.executor.documents import CHECKPOINT, as_dict
from nanoasm.fileio import write_atomic
from nanoasm.schema import Table

SIM_SUFFIX = ".sim"
SIM_FORMAT = "nanoasm.simstate/2"
#: Largest kept world read (bytes): about 2 kB per object and 50 bytes per creeping move.
MAX_SIM_BYTES = 256 * 1024 * 1024


def sim_state_path(log_path: str | os.PathLike) -> Path:
    """Where a dry-run keeps its simulated world beside ``log_path``."""
    p = Path(log_path)
    return p.with_name(p.name + SIM_SUFFIX)


def sim_document(t: float, sim, start_clock: float, initial: tuple[Body, ...]) -> dict:
    """The kept world as JSON types: checkpoint time ``t`` (s), the clock and the truth at
    the start of the run, the world's state."""
    return {"format": SIM_FORMAT, "t": float(t), "start_clock": float(start_clock),
            "initial": [b.to_dict() for b in initial], "world": sim.state_dict()}


class SimKeeper:
    """Dry-run harness subscriber: after every checkpoint, the simulated world and what the
    report needs from before the run (JSON), written atomically to ``path``."""

    def __init__(self, path: str | os.PathLike, sim, start_clock: float, initial: tuple[Body, ...]):
        self.path, self.sim, self.start_clock, self.initial = Path(path), sim, start_clock, initial

    def __call__(self, topic: str, doc) -> None:
        if topic == CHECKPOINT:
            self.keep(float(as_dict(doc).get("t", self.sim.clock())))

    def keep(self, t: float) -> None:
        """The world now, as the one of the checkpoint at instrument time ``t``."""
        text = json.dumps(sim_document(t, self.sim, self.start_clock, self.initial), allow_nan=False,
                          separators=(",", ":"))
        write_atomic(self.path, text, mode=0o600)     # the run's own: for its owner alone


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def read_sim_state(path: str | os.PathLike) -> dict:
    """The kept world's file parsed (JSON only: nothing in it runs) and its outer fields
    checked: ``t``, ``start_clock`` (s), ``initial`` (bodies) and ``world`` (the state,
    checked when :func:`restore_sim` builds it)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(str(path), None, "the simulated world of this dry-run is missing (it is "
                                          "written beside the log as LOG.sim)")
    if p.stat().st_size > MAX_SIM_BYTES:
        raise InputError(str(path), None, f"larger than a kept world can be ({MAX_SIM_BYTES} bytes)")
    data = p.read_bytes()
    try:
        doc = json.loads(data, parse_constant=_no_constant)
    except (ValueError, RecursionError) as err:
        why = ("a pickle, which nanoasm no longer opens: resume a dry-run kept by this version"
               if data[:1] == b"\x80" else f"not JSON: {type(err).__name__}")
        raise InputError(str(path), None, f"unreadable simulated world ({why})") from None
    if not isinstance(doc, dict) or doc.get("format") != SIM_FORMAT:
        raise InputError(str(path), "format", f"not a nanoasm simulated world ({SIM_FORMAT})")
    t = Table(doc, str(path))
    t.check_keys(required=("format", "t", "start_clock", "initial", "world"))
    initial = []
    for bt in t.tables("initial"):
        bt.check_keys(required=("id", "kind", "at", "diameter"), optional=("angle", "length"))
        try:
            initial.append(Body(bt.string("id"), bt.string("kind", choices=("particle", "rod", "wire")),
                                bt.pair("at"), bt.number("diameter", positive=True), bt.number("angle", None),
                                bt.number("length", None)))
        except ValueError as err:
            bt.fail(None, str(err))
    return {"t": t.number("t", nonnegative=True), "start_clock": t.number("start_clock", nonnegative=True),
            "initial": tuple(initial), "world": t.table("world").data}


def restore_sim(path: str | os.PathLike, kept: dict, scene, state: dict | None = None) -> dict:
    """``kept`` (from :func:`read_sim_state`) with ``sim``: the simulated AFM rebuilt over
    ``scene`` (the log's). If ``state`` is given the world must be that checkpoint's.
    Refused, in one line naming ``path``: a world of another scene or another time, a
    field of the wrong type or shape, a number not finite."""
    from nanoasm.world.sim import SimulatedAFM

    if state is not None and not math.isclose(kept["t"], float(state["t"]), rel_tol=0.0, abs_tol=1e-6):
        raise InputError(str(path), None, f"holds the world at t = {kept['t']:.3f} s, but the log's last "
                                          f"checkpoint is at t = {float(state['t']):.3f} s")
    if [b.id for b in kept["initial"]] != [b.id for b in scene.objects]:
        raise InputError(str(path), "initial", "the objects at the start are not the log's scene's")
    try:
        sim = SimulatedAFM.from_state(scene, kept["world"])
    except ValueError as err:
        raise InputError(str(path), "world", str(err)) from None
    return {**kept, "sim": sim}


def load_sim_state(path: str | os.PathLike, scene, state: dict | None = None) -> dict:
    """:func:`read_sim_state` then :func:`restore_sim`: ``t``, ``start_clock``, ``initial``
    and ``sim``, the simulated AFM over ``scene`` as the dry-run kept it."""
    return restore_sim(path, read_sim_state(path), scene, state)
