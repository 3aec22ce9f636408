"""A slot's state after a run, as the report and the run log keep it: the value type of
:mod:`~nanoasm.executor.verdict` and its reader."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: ``filled``: an object of the slot's kind and size within the layout's tolerance;
#: ``missed``: an object was assigned, but none is; ``unfilled``: none was assigned.
STATES = ("filled", "missed", "unfilled")


@dataclass(frozen=True)
class SlotVerdict:
    """One slot's state after the run, the object assigned to it (or None) and the
    centre error (nm) a check scan measured (None: nothing found there)."""

    target: str
    object: str | None
    state: str
    error: float | None

    def __post_init__(self) -> None:
        if self.state not in STATES:
            raise ValueError(f"state must be one of {', '.join(STATES)}, got {self.state!r}")
        if self.error is not None and not (math.isfinite(self.error) and self.error >= 0):
            raise ValueError(f"error must be a non-negative number or None, got {self.error!r}")

    def to_dict(self) -> dict:
        return {"target": self.target, "object": self.object, "state": self.state,
                "error": None if self.error is None else float(self.error)}


def verdict_from_table(t, prefix: str = "slots") -> tuple[SlotVerdict, ...]:
    """The ``slots`` of a report or result document (a :class:`~nanoasm.schema.Table`)."""
    out = []
    for i, st in enumerate(t.tables(prefix), start=1):
        st.check_keys(required={"target", "object", "state", "error"})
        state = st.string("state")
        if state not in STATES:
            st.fail("state", f"must be one of {', '.join(STATES)}, got {state!r}")
        obj = None if st.is_null("object") else st.string("object")
        err = None if st.is_null("error") else st.number("error", nonnegative=True)
        out.append(SlotVerdict(st.string("target"), obj, state, err))
    return tuple(out)
