"""Progress documents: how far a run is, for progress displays alone (the run log keeps
none of them; :mod:`nanoasm.progress` turns them into log lines and a progress bar)."""

from __future__ import annotations

from dataclasses import dataclass

#: How far the run is, for progress displays alone (:class:`ProgressDoc`): the run log keeps none.
PROGRESS = "progress"
#: The phases of a run, in order (a resumed run goes straight to execute); ``drift`` only
#: where the estimator measures the drift before planning.
PHASES = ("full scan", "identify", "drift", "plan", "execute", "repair")


@dataclass(frozen=True)
class ProgressDoc:
    """A step of the run for progress displays: ``step`` "phase" (the run enters phase
    ``text``, one of :data:`PHASES`), "local scan" (one done) or "push" (one streamed: each
    leg of a push in legs counts, as the ledger counts pushes); ``text`` says what it did."""

    step: str
    text: str

    def __post_init__(self) -> None:
        if self.step not in ("phase", "local scan", "push"):
            raise ValueError(f"unknown progress step {self.step!r}; one of phase, local scan, push")
        if self.step == "phase" and self.text not in PHASES:
            raise ValueError(f"unknown phase {self.text!r}; one of {', '.join(PHASES)}")

    def to_dict(self) -> dict:
        return {"step": self.step, "text": self.text}


__all__ = ["PHASES", "PROGRESS", "ProgressDoc"]
