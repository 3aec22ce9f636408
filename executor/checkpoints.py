"""Checkpoints: the whole state of an assembly run as JSON, composed of its components'
``state_dict()``s, and the run set up again from one (see :mod:`nanoasm.executor.resume`).

What never changes during a run, the identified environment, the first plan and the
first full scan, is not repeated in a checkpoint: a run log holds them once
(``/environment``, the first ``/plan``, ``/full_scan``), and :func:`restore` takes them
as ``env``, ``first_plan`` and ``full_scan`` (a HeightImage in the layout frame, or None)
beside the state (:func:`nanoasm.executor.resume.resume_point` puts them there).
"""

from __future__ import annotations

import time

from nanoasm.planner import Operation

from .belief import Belief
from .context import RunContext
from .course import Course
from .estimators import estimator_from_state
from .json_parts import PartCache, Parts, PartsDict
from .pivots import Pivots
from .landmarks import Landmarks
from .ledger import RunLedger
from .reference_choice import LineTiming
from .references import References
from .slot_verdict import SlotVerdict

FORMAT = "nanoasm.checkpoint/1"


def checkpoint(asm, remaining: list[Operation], done: int, corrections: dict[str, int], t: float,
               checked=None) -> dict:
    """What :meth:`Assembly.resume` needs to go on after ``done`` operations of the
    current plan, ``remaining`` to run (JSON types, lossless), and the latest drift
    estimate (``drift``). The ledger's figures are at the top level (``counts``,
    ``times``, ...), where a reader of a log finds them. ``checked``: the slot verdicts
    of the run's last check scans, given to the checkpoint after them, from which a
    resumed run only reports (without them it scanned every slot again: six local scans
    counted twice on the particle bowtie)."""
    ctx, rp = asm.ctx, asm.replanner
    plan, base = _plan_parts(rp.plan, rp.base)
    last = {} if checked is None else {"checked": [v.to_dict() for v in checked]}
    return PartsDict({**last,
        "format": FORMAT, "t": t, "saved_at": time.time(), "strategy": asm.strategy.value,
        "contact_batch": asm.options.contact_batch, "plan": plan, "base": base,
        "remaining": _remaining(remaining), "done": done, "corrections": dict(corrections),
        "belief": ctx.belief.state_dict(), "estimator": ctx.drift.state_dict(),
        "references": ctx.refs.state_dict(), "course": asm.course.state_dict(),
        "landmarks": ctx.landmarks.state_dict(), "line_timing": ctx.timing.state_dict(),
        "pivots": ctx.pivots.state_dict(), "last_after": ctx.last_after,
        "moving": sorted(ctx.moving), **ctx.ledger.state_dict(),
        "drift": ctx.ledger.drift[-1] if ctx.ledger.drift else None})


#: The plan's and base environment's kept parts: neither changes (a replan makes new ones).
_PLAN_PARTS = PartCache()


def _plan_parts(plan, base) -> tuple:
    """``plan.to_dict()`` and ``base.to_dict()`` (None for None), each the same kept part
    (:mod:`.json_parts`) while it stands."""
    items = [(name, part) for name, part in (("plan", plan), ("base", base)) if part is not None]
    made = dict(zip((name for name, _ in items), _PLAN_PARTS.parts(items, lambda p: p.to_dict())))
    return made.get("plan"), made.get("base")


#: The operations still to run, each a kept part while it stands (the same object): a
#: plan's operations stand from one push to the next, and at 1000 objects hundreds remain.
_OPERATIONS = PartCache()


def _remaining(remaining: list[Operation]) -> Parts:
    """``[o.to_dict() for o in remaining]``, each operation's dict the same kept part while
    the operation (frozen) stands."""
    return Parts(_OPERATIONS.parts(((id(o), o) for o in remaining), lambda o: o.to_dict()))


def checkpoint_batch(st: dict) -> int | None:
    """The ``ExecOptions.contact_batch`` the run of checkpoint state ``st`` pushed with, for
    its resumption (None, the default, for a checkpoint written before it was kept)."""
    return None if st.get("contact_batch") is None else int(st["contact_batch"])


def restore(asm, config, st: dict) -> tuple[list[Operation], int, dict[str, int]]:
    """Set ``asm`` up from :func:`checkpoint`'s state; returns (remaining, done, corrections)."""
    from nanoasm.planner.plan import plan_from_dict
    from nanoasm.world.environment import environment_from_dict

    if st.get("format") != FORMAT:
        raise ValueError(f"not a nanoasm checkpoint (format {st.get('format')!r})")
    if st["strategy"] != asm.strategy.value:
        raise ValueError(f"the run used strategy {st['strategy']!r}, not {asm.strategy.value!r}")
    asm.env = environment_from_dict(st["env"], "checkpoint")
    asm.first_plan = plan_from_dict(st["first_plan"], "checkpoint")
    asm.registered(asm.first_plan.registration)     # a layout registered by its marks: the scan's frame
    rp = asm.replanner
    rp.plan = plan_from_dict(st["plan"], "checkpoint") if st["plan"] else None
    rp.base = environment_from_dict(st["base"], "checkpoint") if st["base"] else None
    carrier = st["plan"] or st["first_plan"]       # a plan document around the operations
    remaining = list(plan_from_dict({**carrier, "operations": st["remaining"]}, "checkpoint").operations)
    asm.ctx = RunContext(config, asm.options, estimator_from_state(st["estimator"], asm.options),
                         Belief.from_state(st["belief"]), References.from_state(st["references"]),
                         RunLedger.from_state(st), moving=set(st["moving"]))
    asm.course = Course.from_state(st["course"])
    asm.ctx.landmarks = Landmarks.from_state(st.get("landmarks"))
    asm.ctx.pivots = Pivots.from_state(st.get("pivots"))
    asm.ctx.last_after = st.get("last_after")
    if st.get("line_timing"):
        asm.ctx.timing = LineTiming.from_state(st["line_timing"])
    asm.ctx.full_scan, asm.ctx.env_objects = st.get("full_scan"), asm.env.objects
    if st.get("checked") is not None:
        asm.slots = tuple(SlotVerdict(**v) for v in st["checked"])
    return remaining, int(st["done"]), {k: int(v) for k, v in st["corrections"].items()}
