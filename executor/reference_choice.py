"""Which drift reference to scan: the one that gives the most information per second.

A reference measures the offset (an untouched particle: both coordinates) or some of
its components (a fixed feature's straight edge: the coordinate normal to it; a corner:
both). Its information is the reduction of the offset covariance's trace it would bring
(``trace C - trace (C⁻¹ + Hᵀ R⁻¹ H)⁻¹``, nm²), its cost the instrument seconds its
lines take (learnt from the instrument's own clock, :class:`LineTiming`) plus the
travel to them and the creep that travel brings (:func:`travel_cost`); the choice is
the largest ratio (ties by id, so runs are repeatable).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Covariance (nm² per axis) assumed for a located centre when choosing references.
LOCATED_VAR = 4.0
#: Seconds per line and per sample assumed until the instrument has shown its own.
DEFAULT_LINE_OVERHEAD = 0.2
DEFAULT_SAMPLE_TIME = 0.001
#: What a long travel to a reference costs besides its time: its creep (a 5 µm move
#: creeps some 150 nm over the next minutes, known to ±30 %), which the following
#: pushes pay for; counted as this many seconds per nm of travel, there and back.
CREEP_COST = 1.0 / 1000.0


def travel_cost(here, there, max_speed: float) -> float:
    """Seconds a reference ``there`` costs for its travel from ``here`` (scanner frame,
    nm): the travel itself and :data:`CREEP_COST` for its creep; nothing if ``here`` is
    unknown."""
    if here is None:
        return 0.0
    d = math.dist(here, there)
    return d / max_speed + 2.0 * d * CREEP_COST


@dataclass(frozen=True, eq=False)
class Candidate:
    """A reference that could be scanned: ``kind`` "object" or "feature", its ``id``,
    what it measures (``H`` (m, 2) directions, ``R`` (m, m) nm²), its cost in
    instrument seconds and its information (nm² of trace)."""

    kind: str
    id: str
    H: np.ndarray
    R: np.ndarray
    seconds: float
    gain: float

    @property
    def rate(self) -> float:
        """Information per second, nm²/s."""
        return self.gain / max(self.seconds, 1e-9)


def object_candidates(ctx, est, t: float, full_scan_var: float) -> list[Candidate]:
    """Untouched particles as references for the estimator ``est`` at ``t``: never
    pushed, not quarantined, not moved by the plan, not cut by the image border; each
    measured against where the full scan saw it (``full_scan_var`` nm² per axis). The
    filter's algebra is done for all of them at once (:func:`_terms`)."""
    ids = _usable(ctx)
    return _weighed(ctx, est, t, ids, full_scan_var, est.offset(t)) if ids else []


def best_object(ctx, est, t: float, full_scan_var: float, exclude=frozenset()) -> Candidate | None:
    """What :func:`best` chooses of :func:`object_candidates` (those in ``exclude`` left
    out), without weighing the candidates that cannot beat it. A measurement removes at
    most the offset's whole variance (the trace of the filter's covariance), and a candidate's
    seconds are at least those of its lines at the least ``r_max`` plus its travel; so
    its rate is at most that trace over those seconds. Candidates are weighed in batches
    of :data:`BATCH`, highest bound first, until no bound left reaches the best rate (a
    1000-object run has hundreds of candidates at every choice, the best of them near)."""
    exclude = set(exclude)
    ids = [oid for oid in _usable(ctx) if oid not in exclude]
    if not ids:
        return None
    off = est.offset(t)
    trace = float(np.trace(est.filter.offset(est.clamp(t)).cov)) * (1.0 + 1e-9)    # what the gains are of
    floor = ctx.options.line_factor * ctx.options.r_max_floor
    at = ctx.positions(ids)
    bounds = np.array([trace / max(_seconds(ctx, oid, floor, off, at[k]), 1e-9) for k, oid in enumerate(ids)])
    order = np.argsort(-bounds, kind="stable")
    chosen = None
    for start in range(0, len(order), BATCH):
        if chosen is not None and bounds[order[start]] < chosen.rate:
            break
        batch = [ids[k] for k in order[start:start + BATCH]]
        chosen = best([*([chosen] if chosen is not None else []),
                       *_weighed(ctx, est, t, batch, full_scan_var, off)])
    return chosen


def best_reference(ctx, est, t: float, full_scan_var: float, features, exclude=()) -> Candidate | None:
    """:func:`best` of the objects' candidates (:func:`best_object`) and the fixed
    features' ``features``, those in ``exclude`` left out."""
    found = best_object(ctx, est, t, full_scan_var, exclude)
    return best([*([found] if found is not None else []), *(c for c in features if c.id not in exclude)])


#: Candidates weighed together by :func:`best_object`.
BATCH = 32


def _usable(ctx) -> list[str]:
    belief, refs = ctx.belief, ctx.refs
    return [oid for oid, o in belief.objects.items()
            if refs.usable(oid, ctx.ledger.pushed, belief.lost) and oid not in belief.touched
            and oid not in ctx.moving and o.kind == "particle" and not o.edge]


def _seconds(ctx, oid, r_max: float, off, at) -> float:
    """Instrument seconds of a reference scan of ``oid`` (two lines through it, ``r_max``
    nm on either side beyond its radius and margin) and of the travel to it from its
    believed position ``at`` (:meth:`~.context.RunContext.positions`)."""
    o = ctx.belief[oid]
    spacing, margin = ctx.scan_opts.sampling(o.diameter)
    length = 2 * (o.radius + r_max + margin)
    return (ctx.timing.seconds(2, 2 * int(length / spacing))
            + travel_cost(ctx.here, at + off, ctx.config.max_speed))


def _weighed(ctx, est, t: float, ids, full_scan_var: float, off) -> list[Candidate]:
    R = np.eye(2) * (LOCATED_VAR + full_scan_var)
    full_scan, gains = _terms(ctx, est, t, ids, R)
    at = ctx.positions(ids)
    return [Candidate("object", oid, np.eye(2), R, _seconds(ctx, oid, ctx.r_max(t, oid, full_scan[k]), off, at[k]),
                      float(gains[k])) for k, oid in enumerate(ids)]


def _terms(ctx, est, t: float, ids, R) -> tuple[np.ndarray, np.ndarray]:
    """For each of the objects ``ids``: the covariance of where its full-scan row lies at
    ``t`` (:meth:`~.kalman_drift.Kalman.full_scan_cov`; what :meth:`RunContext.r_max` adds
    for an object seen only in the full scan, whose sighting is that row's) and the
    information its scan would give (:meth:`~.kalman_drift.Kalman.information`), (K, 2, 2)
    and (K,). Once the filter holds the full scan's drift model, both come from one
    batched projection (a thousand candidates at every reference choice of a 1000-object
    run: 0.4 s a choice one by one); before, one by one."""
    taus = [ctx.refs.first_seen[oid][1] - est.epoch for oid in ids]
    statics = [est.static_rows(np.eye(2), [tau, tau]) for tau in taus]
    if not est.filter.statics:
        return (np.array([est.full_scan_cov(t, tau) for tau in taus]),
                np.array([est.information(t, np.eye(2), s, R) for s in statics]))
    return est.filter.weigh_many(est.clamp(t), np.eye(2), R, np.array(statics))


def best(candidates) -> Candidate | None:
    """The candidate of most information per second (None if there is none)."""
    cands = [c for c in candidates if c.gain > 0.0]
    return max(cands, key=lambda c: (c.rate, c.id)) if cands else None


@dataclass
class LineTiming:
    """What one local-scan line costs on this instrument: ``overhead + samples * per_sample``
    seconds, fitted by least squares to the lines scanned so far (defaults until two
    different lengths were seen); and ``approach``, the seconds a push's first write into
    contact took beyond its samples after scanning (the switch into contact mode, 2 s on
    the simulator), the mean of those seen so far (0 until one was), with ``tapping``:
    whether the tip scanned since the last push, so that the next push switches (not kept
    in checkpoints: a resumed run starts as after scanning)."""

    n: int = 0
    s_x: float = 0.0
    s_y: float = 0.0
    s_xx: float = 0.0
    s_xy: float = 0.0
    approach: float = 0.0
    approaches: int = 0
    tapping: bool = True

    def switched(self, samples: int, seconds: float) -> float:
        """What of a line of ``samples`` that took ``seconds`` was a mode switch before it:
        the time beyond its predicted cost when it took far longer (twice that and half a
        second more), else 0."""
        if self.n < 2 or not math.isfinite(seconds):
            return 0.0
        predicted = self.seconds(1, samples)
        return seconds - predicted if seconds > 2.0 * predicted + 0.5 else 0.0

    def observe(self, samples: int, seconds: float) -> None:
        """One line of ``samples`` took ``seconds``; a line that took far longer than
        predicted (a mode switch before it) is left out."""
        if not (math.isfinite(seconds) and seconds >= 0.0):
            return
        if self.switched(samples, seconds) > 0.0:
            return
        x = float(samples)
        self.n += 1
        self.s_x += x
        self.s_y += seconds
        self.s_xx += x * x
        self.s_xy += x * seconds

    def fit(self) -> tuple[float, float]:
        """``(overhead s, seconds per sample)``."""
        det = self.n * self.s_xx - self.s_x ** 2
        if self.n < 2 or det <= 1e-9 * max(self.s_xx, 1.0) * max(self.n, 1):
            return DEFAULT_LINE_OVERHEAD, DEFAULT_SAMPLE_TIME
        per = (self.n * self.s_xy - self.s_x * self.s_y) / det
        over = (self.s_y - per * self.s_x) / self.n
        return max(over, 0.0), max(per, 0.0)

    def seconds(self, lines: int, samples: int) -> float:
        """Predicted seconds of ``lines`` lines holding ``samples`` samples in all."""
        over, per = self.fit()
        return lines * over + samples * per

    def switch_ahead(self) -> float:
        """Seconds the next push's first sample is expected to wait for the switch into
        contact: :attr:`approach` after scanning, else 0."""
        return self.approach if self.tapping else 0.0

    def pushed(self, extra: float) -> None:
        """A push's write into contact took ``extra`` seconds beyond its samples: after
        scanning, the switch into contact, folded into :attr:`approach`."""
        if self.tapping and math.isfinite(extra) and extra >= 0.0:
            self.approaches += 1
            self.approach += (extra - self.approach) / self.approaches
        self.tapping = False

    def state_dict(self) -> dict:
        return {"n": self.n, "sums": [self.s_x, self.s_y, self.s_xx, self.s_xy],
                "approach": [self.approach, self.approaches]}

    @classmethod
    def from_state(cls, state: dict) -> LineTiming:
        approach, k = state.get("approach", (0.0, 0))      # a checkpoint from before it was kept: unknown
        return cls(int(state["n"]), *(float(v) for v in state["sums"]), float(approach), int(k))
