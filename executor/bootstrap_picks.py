"""What the drift bootstrap scans again, and in what order (:class:`Picks`).

The bootstrap's first references are scanned while the drift since the full scan is
known only from its prior: at 0.5 nm/s, a reference seen 570 s before is 285 nm (1σ)
from where the scan has it, and its lines are that long. Among neighbours, a search that
long finds one of them as well as the reference; a neighbour taken for an early reference
gives a wrong velocity, the next references' lines are laid where they are not, and the
widened searches that follow take more neighbours (``scale1000`` seeds 7 and 10: the
bootstrap's estimate 6.5 and 10.4 µm off). So each stretch of the full scan's rows gives
its roomiest particle or corner: the one farthest from any other object (gaps above
:data:`ROOMY_ENOUGH` count alike, and then the one nearest the stretch's end of the
rows, whose lever on the velocity is the longest).
"""

from __future__ import annotations

import math

import numpy as np
import shapely

#: A gap (nm) from a reference to its nearest neighbour beyond which more room does not
#: matter: longer than the bootstrap's searches (up to the lost search's 1.5 µm radius,
#: which few references need).
ROOMY_ENOUGH = 1000.0
#: Picks of a stretch not found in a row before the other stretches come first.
TRIES = 3

#: An early reference (:func:`early_choice`) is scanned only when it is expected to
#: shrink the σ (largest direction) of the drift since the scan began to this fraction
#: or less,
EARLY_GAIN = 0.8
#: ... and only while that σ is above this, nm: below it, 3σ of where the layout's frame
#: lies is within a slot's 20 nm tolerance with room for a push's error, and with 3 nm
#: here early references changed the drift RMS of the sparse and dense runs they were
#: scanned in (the filter's σ after the bootstrap 2.4-3.8 nm) by -2.0 to +2.8 nm, for
#: one or two more local scans (seeds 1-10).
EARLY_FLOOR = 5.0
#: Room (nm) beyond its lines' 3σ reach an early reference wants from its neighbours.
EARLY_MARGIN = 60.0
#: Variance (nm²) of a located centre's component, as the choice assumes it.
EARLY_LOCATED_VAR = 4.0


class Picks:
    """What the bootstrap may scan again, in order: ``(kind, id, time seen)``, from
    ``count`` equal stretches of the full scan's rows, each stretch's candidates roomiest
    first (:func:`gaps`), and straight edges after them, latest first. Each next pick
    comes from the stretch with the fewest references so far (:meth:`found`,
    :meth:`left_out`), the latest first among those: one from each stretch, latest first
    (their drift since is the smallest, so their lines are short, and every one sharpens
    the velocity that sizes the next one's lines), a pick not found or left out replaced
    from its own stretch (a tear of the scan, 300 nm at its middle, put the corners of the
    early rows out of their searches' reach; replaced by the latest rows' picks, no
    reference before the tear was left to show it), a stretch that failed
    :data:`TRIES` times in a row only when every other one has too. Particles and corners measure both
    coordinates; straight edges follow them."""

    def __init__(self, belief, marks, count: int):
        both = [("object", o.id, belief.seen[o.id].t) for o in belief.objects.values()
                if o.kind == "particle" and not o.edge]
        feats = [("feature", fid, float(np.mean(marks.seen[fid]))) for fid in marks.features]
        both += [c for c in feats if marks.features[c[1]].kind == "corner"]
        self.edges = sorted((c for c in feats if c not in both), key=lambda c: (-c[2], c[1]))
        both.sort(key=lambda c: (c[2], c[1]))
        k = min(count, len(both))
        room = np.minimum(gaps(belief, marks, both), ROOMY_ENOUGH)
        self.stretches = []
        for j, stretch in enumerate(np.array_split(np.arange(len(both)), k) if k else ()):
            end = j * (len(both) - 1) / max(k - 1, 1)      # where an even spread would pick
            self.stretches.append([both[i] for i in sorted(stretch, key=lambda i: (-room[i], abs(i - end), i))])
        self.stretches.reverse()                        # latest first
        self.have = [0] * len(self.stretches)
        self.failed = [0] * len(self.stretches)
        self._of: dict = {}                             # id -> its stretch
        self._last: int | None = None

    def __iter__(self):
        while True:
            open_ = [j for j, s in enumerate(self.stretches) if s]
            if not open_:
                break
            j = min(open_, key=lambda j: (self.failed[j] >= TRIES, self.have[j], j))
            self.failed[j] += 1                         # until found
            yield self._take(j)
        self._last = None
        yield from self.edges

    def latest(self):
        """Picks of the latest rows' stretch still unscanned, at most :data:`TRIES`."""
        for _ in range(TRIES):
            if not self.stretches or not self.stretches[0]:
                return
            yield self._take(0)

    def _take(self, j: int, i: int = 0):
        """Pick ``i`` of stretch ``j`` (by default its next), taken out and remembered as the last."""
        pick = self.stretches[j].pop(i)
        self._of[pick[1]], self._last = j, j
        return pick

    def between(self, t0: float, t1: float) -> list:
        """Unscanned particles whose row lies between ``t0`` and ``t1`` (s; not corners,
        whose sites lie on several rows)."""
        return [p for s in self.stretches for p in s if p[0] == "object" and t0 < p[2] < t1]

    def take(self, pick) -> None:
        """Take ``pick`` (of :meth:`between`) out of its stretch, remembered as the last."""
        for j, s in enumerate(self.stretches):
            if pick in s:
                self._take(j, s.index(pick))
                return

    def put_back(self, pick) -> None:
        """``pick``, scanned but not measured, may be picked again (by :meth:`between`
        too): back at the end of its stretch."""
        j = self._of.get(pick[1])
        if j is not None and pick not in self.stretches[j]:
            self.stretches[j].append(pick)

    def forget(self, rid: str) -> None:
        """``rid`` is no object of its own (:func:`~.tear_doubles.doubles`): never picked."""
        for s in self.stretches:
            s[:] = [p for p in s if p[1] != rid]

    def found(self) -> None:
        """The last pick measured the drift."""
        if self._last is not None:
            self.have[self._last] += 1
            self.failed[self._last] = 0

    def left_out(self, rid: str) -> None:
        """Pick ``rid`` was left out again: its stretch gives another."""
        j = self._of.get(rid)
        if j is not None:
            self.have[j] -= 1

    def taken_back(self, rid: str) -> None:
        """Pick ``rid``, left out, was taken back."""
        j = self._of.get(rid)
        if j is not None:
            self.have[j] += 1


def gaps(belief, marks, cands) -> np.ndarray:
    """Each candidate's gap (nm) to its nearest neighbour as the full scan saw them: a
    particle's to any other believed object's footprint or an obstacle, a corner's (the
    mean of its sites) to any believed object's footprint."""
    objs = list(belief.objects.values())
    if not objs:
        return np.full(len(cands), np.inf)
    tree = shapely.STRtree([o.geometry() for o in objs])
    radius = np.array([o.radius for o in objs])
    walls = shapely.STRtree([shapely.Polygon(ob.polygon) for ob in belief.obstacles]) if belief.obstacles else None
    out = np.full(len(cands), np.inf)
    for i, (kind, rid, _) in enumerate(cands):
        if kind == "object":
            me = belief[rid]
            geom, own = me.geometry(), me.radius
        else:
            geom = shapely.Point(np.mean([s.point for s in marks.features[rid].sites], axis=0))
            own = 0.0
        near = tree.query(geom, predicate="dwithin", distance=ROOMY_ENOUGH + own + radius.max())
        gap = [shapely.distance(geom, tree.geometries[j]) - own - radius[j] for j in near
               if not (kind == "object" and objs[j].id == rid)]
        if kind == "object" and walls is not None:
            gap += [shapely.distance(geom, walls.geometries[j]) - own
                    for j in walls.query(geom, predicate="dwithin", distance=ROOMY_ENOUGH + own)]
        out[i] = min(gap, default=np.inf)
    return out


def spots_room(belief, first: dict, ids: list, jump: np.ndarray) -> dict:
    """Each object's room (nm) about where it is looked for on either side of a tear: the
    least gap from its position in the full scan, and that less and plus the jump, to any
    other object's footprint there."""
    others = [oid for oid in first if oid in belief.objects]
    at = np.array([first[oid][0] for oid in others], float).reshape(-1, 2)
    radius = np.array([belief[oid].radius for oid in others])
    out = {}
    for rid in ids:
        mine = np.array([oid != rid for oid in others])
        p = np.asarray(first[rid][0], float)
        gaps = [np.hypot(*(at[mine] - spot).T) - radius[mine] for spot in (p, p - jump, p + jump)]
        out[rid] = float(min((g.min() for g in gaps if g.size), default=np.inf))
    return out


def early_choice(scan, now: float, cands, var: float):
    """Of ``cands`` (``(pick, τ of its row, room nm)``), the one whose two components
    measured ``now`` (s after the epoch) would shrink the largest σ of the drift since the
    scan began (``scan``'s model) the most, among those whose room holds their lines' 3σ
    reach and :data:`EARLY_MARGIN` (``var``: the variance, nm², a measured component
    carries besides the located centre's): ``(σ before, σ expected after, pick)``, or
    None when σ is below :data:`EARLY_FLOOR` or none shrinks it to :data:`EARLY_GAIN` of
    itself."""
    before = early_sigma(scan, now)
    if before < EARLY_FLOOR:
        return None
    best = None
    for pick, tau, room in cands:
        if room < 3.0 * _largest_std(scan.between_cov(now, tau)) + EARLY_MARGIN:
            continue
        trial = scan.trial()
        for e in ((1.0, 0.0), (0.0, 1.0)):
            trial.measure(np.array(e), 0.0, now, tau, var + EARLY_LOCATED_VAR)
        after = _largest_std(trial.offset_cov(now))
        if best is None or after < best[1]:
            best = (before, after, pick)
    return best if best is not None and best[1] <= EARLY_GAIN * before else None


def early_sigma(scan, now: float) -> float:
    """The largest σ (nm) of the drift since the scan began, ``now`` s after the epoch,
    by ``scan``'s model: below :data:`EARLY_FLOOR` no early reference is looked for."""
    return _largest_std(scan.offset_cov(now))


def _largest_std(cov: np.ndarray) -> float:
    """The largest standard deviation of a 2-D covariance, nm."""
    return math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))
