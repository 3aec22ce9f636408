"""The run ledger: what a run has done so far, counted (pushes, scans, replans), timed (by
activity on the instrument, by stage of this program's own compute) and what went wrong
(failures by cause, troubles per object)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .report import Counts

#: Activities the instrument's time is split into, s: ``mode_switch``, the approaches from
#: tapping to contact before pushes and the switches back before a scan line (what a line
#: took beyond its learnt cost, :func:`~.scan_steps.scan_line`).
ACTIVITIES = ("full_scan", "local_scan", "push", "travel", "mode_switch")
#: Stages of this program's own compute, wall-clock s.
STAGES = ("identify", "plan", "execute")
#: What the drift measurements' instrument time went on (within the activities), s:
#: reference scans before pushes, relocalisations, the bootstrap after the full scan.
PURPOSES = ("reference", "relocalise", "bootstrap")


@dataclass
class RunLedger:
    """Counts, times and failures of one run (JSON-ready through :meth:`state_dict`).

    ``troubles`` counts, per object, the pushes that failed or went astray; an object
    reaching ``max_failures`` of them is ``given_up`` (left where it is). ``drift`` logs
    the scanner offset of the layout origin ``(t, x, y)`` after each estimate update.
    ``purposes``: the instrument seconds spent measuring drift, by :data:`PURPOSES`
    (counted within ``times`` too).
    """

    counts: dict[str, int] = field(default_factory=lambda: {
        "pushes": 0, "local_scans": 0, "replans": 0, "failed_pushes": 0})
    times: dict[str, float] = field(default_factory=lambda: dict.fromkeys(ACTIVITIES, 0.0))
    wall: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    purposes: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PURPOSES, 0.0))
    failures: list[tuple[str, str]] = field(default_factory=list)
    troubles: dict[str, int] = field(default_factory=dict)
    given_up: set[str] = field(default_factory=set)
    pushed: list[str] = field(default_factory=list)
    drift: list[tuple[float, float, float]] = field(default_factory=list)
    repairs: int = 0                    # repair rounds made (:mod:`.repair`)

    def fail(self, obj_id: str, cause: str) -> None:
        """An object's push or scan went wrong (``cause``: lost, slipped, ...)."""
        self.failures.append((obj_id, cause))

    def trouble(self, obj_id: str, max_failures: int) -> bool:
        """One more push of ``obj_id`` failed or went astray; True when that makes
        ``max_failures`` and the object is given up. One already given up (its push
        beyond the scanner's range) is not counted again."""
        if obj_id in self.given_up:
            return False
        self.troubles[obj_id] = self.troubles.get(obj_id, 0) + 1
        if self.troubles[obj_id] == max_failures:
            self.given_up.add(obj_id)
            return True
        return False

    def pushed_once(self, obj_id: str) -> None:
        if obj_id not in self.pushed:
            self.pushed.append(obj_id)

    def count(self) -> Counts:
        return Counts(**self.counts)

    def state_dict(self) -> dict:
        return {"counts": dict(self.counts), "times": dict(self.times), "wall": dict(self.wall),
                "purposes": dict(self.purposes),
                "failures": [list(f) for f in self.failures], "troubles": dict(self.troubles),
                "given_up": sorted(self.given_up), "pushed": list(self.pushed),
                "drift_log": [list(d) for d in self.drift], "repairs": self.repairs}

    @classmethod
    def from_state(cls, state: dict) -> RunLedger:
        out = cls()
        out.counts.update({k: int(v) for k, v in state["counts"].items()})
        out.times.update({k: float(v) for k, v in state["times"].items()})
        out.wall.update({k: float(v) for k, v in state["wall"].items()})
        out.purposes.update({k: float(v) for k, v in state.get("purposes", {}).items()})
        out.failures = [tuple(f) for f in state["failures"]]
        out.troubles = {k: int(v) for k, v in state["troubles"].items()}
        out.given_up = set(state["given_up"])
        out.pushed = list(state["pushed"])
        out.repairs = int(state.get("repairs", 0))
        out.drift = [tuple(d) for d in state["drift_log"]]
        return out
