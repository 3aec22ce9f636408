"""The whole state of an assembly run as JSON, for checkpoints and resuming.

A mixin of :class:`~nanoasm.executor.assembly.Assembly`: :meth:`RunState.state_dict`
writes what :meth:`RunState._restore` reads back (see :mod:`nanoasm.executor.resume`).
"""

from __future__ import annotations

import time

import numpy as np

from nanoasm.drift import DriftFilter, DriftFilterParams
from nanoasm.planner import Operation

from .belief import Belief


class RunState:
    """Checkpoint state of an :class:`Assembly`."""

    def _checkpoint(self, ops: list[Operation], i: int, done: int, corrections: dict[str, int],
                    t: float) -> dict:
        """The checkpoint document: :meth:`state_dict` and the latest drift estimate."""
        return {**self.state_dict(ops[i:], done, corrections, t),
                "drift": self.drift_log[-1] if self.drift_log else None}

    def state_dict(self, remaining: list[Operation], done: int, corrections: dict[str, int],
                   t: float) -> dict:
        """What :meth:`resume` needs to go on after ``done`` operations of the current plan,
        ``remaining`` to run (JSON types, lossless). What never changes during a run, the
        identified environment and the first plan, is not repeated here: a run log holds
        them once (``/environment``, the first ``/plan``), and :meth:`_restore` takes them
        as ``env`` and ``first_plan`` beside the state
        (:func:`nanoasm.executor.resume.resume_point` puts them there)."""
        return {
            "format": "nanoasm.checkpoint/1", "t": t, "saved_at": time.time(), "strategy": self.strategy.value,
            "epoch": self.epoch, "origin": [float(v) for v in self.origin],
            "plan": None if self.replanner.plan is None else self.replanner.plan.to_dict(),
            "base": None if self.replanner.base is None else self.replanner.base.to_dict(),
            "remaining": [o.to_dict() for o in remaining], "done": done,
            "corrections": dict(corrections), "belief": self.belief.state_dict(),
            "filter": self.filter.state_dict() if self.filter is not None else None,
            "raw": sorted(self.raw), "first_seen": {k: [float(a[0]), float(a[1]), float(ts)]
                                                    for k, (a, ts) in self.first_seen.items()},
            "no_reference": sorted(self.no_reference), "pushed": list(self.pushed),
            "troubles": dict(self.troubles), "given_up": sorted(self.given_up),
            "moving": sorted(self.moving), "preload_factor": dict(self.preload_factor),
            "plan_start": {str(k): [list(at), ang] for k, (at, ang) in self._plan_start.items()},
            "creep_anchor": None if self._creep_anchor is None else [float(v) for v in self._creep_anchor],
            "anchor": None if self.anchor is None else [self.anchor[0], list(self.anchor[1])],
            "anchor_offset": [float(v) for v in self.anchor_offset],
            "counts": dict(self.counts), "times": dict(self.times), "wall": dict(self.wall),
            "failures": [list(f) for f in self.failures],
            "drift_log": [list(d) for d in self.drift_log]}

    def _restore(self, st: dict) -> tuple[list[Operation], int, dict[str, int]]:
        """Set the run's state from :meth:`state_dict`; returns (remaining, done, corrections)."""
        from nanoasm.planner.plan import plan_from_dict
        from nanoasm.world.environment import environment_from_dict

        if st.get("format") != "nanoasm.checkpoint/1":
            raise ValueError(f"not a nanoasm checkpoint (format {st.get('format')!r})")
        if st["strategy"] != self.strategy.value:
            raise ValueError(f"the run used strategy {st['strategy']!r}, not {self.strategy.value!r}")
        self.epoch, self.origin = float(st["epoch"]), np.asarray(st["origin"], float)
        self.env = environment_from_dict(st["env"], "checkpoint")
        self.first_plan = plan_from_dict(st["first_plan"], "checkpoint")
        self.replanner.plan = plan_from_dict(st["plan"], "checkpoint") if st["plan"] else None
        self.replanner.base = environment_from_dict(st["base"], "checkpoint") if st["base"] else None
        carrier = st["plan"] or st["first_plan"]       # a plan document around the operations
        remaining = list(plan_from_dict({**carrier, "operations": st["remaining"]}, "checkpoint").operations)
        self.belief = Belief.from_state(st["belief"])
        if st["filter"] is not None:
            o = self.options
            self.filter = DriftFilter.from_state(
                DriftFilterParams(q=o.drift_q, q_offset=o.drift_q_offset, offset_std=1.0), st["filter"])
        self.raw = set(st["raw"])
        self.first_seen = {k: (np.array(v[:2], float), float(v[2])) for k, v in st["first_seen"].items()}
        self.no_reference = set(st["no_reference"])
        self.troubles = {k: int(v) for k, v in st["troubles"].items()}
        self.given_up = set(st["given_up"])
        self.pushed = list(st["pushed"])
        self.moving = set(st["moving"])
        self.preload_factor = {k: float(v) for k, v in st["preload_factor"].items()}
        self._plan_start = {int(k): (tuple(v[0]), v[1]) for k, v in st["plan_start"].items()}
        self._creep_anchor = None if st["creep_anchor"] is None else np.asarray(st["creep_anchor"], float)
        self.anchor = None if st["anchor"] is None else (st["anchor"][0], tuple(st["anchor"][1]))
        self.anchor_offset = np.asarray(st["anchor_offset"], float)
        self.counts.update({k: int(v) for k, v in st["counts"].items()})
        self.times.update({k: float(v) for k, v in st["times"].items()})
        self.wall.update({k: float(v) for k, v in st["wall"].items()})
        self.failures = [tuple(f) for f in st["failures"]]
        self.drift_log = [tuple(d) for d in st["drift_log"]]
        return remaining, int(st["done"]), {k: int(v) for k, v in st["corrections"].items()}
