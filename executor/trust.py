"""When a drift estimate can no longer be trusted: the references rejected in a row, the
stand-still of a resumed run, and when the estimate was last relocalised or failed to be
(:class:`Trust`, a part of :class:`~nanoasm.executor.kalman_drift.Kalman`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .strategy import ExecOptions


@dataclass
class Trust:
    """``rejected``: the references rejected in the present streak, in order (since
    ``streak_start``, instrument s); ``pause``: the stand-still (s) of the last resume;
    ``failed_at``/``relocalised_at``: when a relocalisation last failed/succeeded;
    ``confirmed_at``: when a reference (or a relocalisation) last agreed with the estimate.
    A drift jump happened after ``confirmed_at`` and, when a streak of rejections led to
    a relocalisation, before ``streak_start``."""

    rejected: list[str] = field(default_factory=list)
    streak_start: float | None = None
    pause: float = 0.0
    failed_at: float | None = None
    relocalised_at: float | None = None
    confirmed_at: float | None = None

    @property
    def rejections(self) -> int:
        """Different references in the streak (one reference out of place again and
        again is its own trouble, not the estimate's)."""
        return len(set(self.rejected))

    def reject(self, label: str, t: float) -> None:
        """A reference was rejected, or not found where it should be, at ``t``."""
        if not self.rejected:
            self.streak_start = float(t)
        self.rejected.append(label)

    def accept(self, t: float | None = None) -> None:
        """A reference agreed (at ``t``, when given): the streak ends."""
        self.rejected, self.streak_start = [], None
        if t is not None:
            self.confirmed_at = float(t)

    def needs(self, t: float, sigma: float, options: ExecOptions) -> tuple[str, str] | None:
        """Why the estimate (of σ ``sigma`` nm at ``t``) must be relocalised, as ``(kind,
        text)`` with kind "pause", "rejections" or "sigma"; None: it need not, or a
        relocalisation failed less than ``relocalise_pause`` ago."""
        if self.failed_at is not None and t - self.failed_at < options.relocalise_pause:
            return None
        if self.pause >= options.relocalise_pause:
            return "pause", f"resumed after {self.pause:.0f} s"
        if self.rejections >= options.relocalise_rejections:
            return "rejections", (f"{self.rejections} references in a row ({', '.join(self.rejected)}) "
                                  f"were not where the estimate put them")
        recent = self.relocalised_at is not None and t - self.relocalised_at < options.relocalise_pause
        if sigma > options.relocalise_sigma and not recent:
            return "sigma", f"the drift estimate's σ reached {sigma:.0f} nm"
        return None

    def relocalised(self, t: float) -> list[str]:
        """Relocalised at ``t``: the references the streak rejected did not move, the
        drift did; returns them (to re-admit) and ends the streak."""
        forgiven = sorted(set(self.rejected))
        self.accept(t)
        self.pause, self.failed_at, self.relocalised_at = 0.0, None, float(t)
        return forgiven

    def failed(self, t: float) -> None:
        """No window registered at ``t``: go on as before, without retrying for a while."""
        self.accept()
        self.pause, self.failed_at = 0.0, float(t)

    def state_dict(self) -> dict:
        return {"rejected": list(self.rejected), "streak_start": self.streak_start,
                "failed_at": self.failed_at, "relocalised_at": self.relocalised_at,
                "confirmed_at": self.confirmed_at}

    @classmethod
    def from_state(cls, state: dict) -> Trust:
        """From :meth:`state_dict`'s keys (missing ones: a fresh trust)."""
        return cls(list(state.get("rejected", [])), state.get("streak_start"), 0.0,
                   state.get("failed_at"), state.get("relocalised_at"), state.get("confirmed_at"))


__all__ = ["Trust"]
