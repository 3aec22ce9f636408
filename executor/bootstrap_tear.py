"""The bootstrap's jump of the drift placed (:mod:`.drift_bootstrap`): taken into its model
once evident (:func:`jumped`), a tear told from a jump after the scan by a reference scanned
once more (:func:`tear_or_jump`, :func:`told_again`), and a tear narrowed by the objects of
the rows around it (:func:`narrow_tear`). ``rows_of`` is the bootstrap's scan of one
reference, ``(ctx, kind, id, seen_t, widen)`` -> ``(rows, time, seen)`` or None
(:func:`~.drift_bootstrap._bootstrap_rows`)."""

from __future__ import annotations

import itertools
import math

from . import bootstrap_picks
from .context import RunContext
from .engine import Msg
from .scan_drift import JUMP_GATE
from .scan_jump import scanned_before, tear_band

#: Objects of the rows between the two references around a tear looked for on either side
#: of it (:func:`narrow_tear`), each halving the rows it may lie in.
TEAR_PROBES = 6
#: Room (nm) from any other object's footprint a probe of a tear wants about where it
#: is looked for, on either side (the jump apart), before it is chosen for lying halfway:
#: a search reaches its lines' margin and the object's radius beyond its 3σ (15 + 55 + 45
#: nm for a 90 nm particle), and where the side is wrong a neighbour there is taken for it
#: (scale300 seed 3, a tear at 1096 s: one 125 nm from the wrong spot put it at 1041 s).
TEAR_ROOM = 250.0


def jumped(scan) -> None:
    """Take a jump of the drift since the full scan began (while it was made, before the
    references are scanned again, or while they are) into the model once they make it
    evident (:data:`JUMP_GATE`); once in, place it again as references are left out or
    added, and out again where it no longer passes the gate (mixed seed 3, a tear at 250 s
    below every reference's row: the first references made a jump of 120 nm evident, the
    ones scanned after them did not). Without it a jump is taken for velocity: 300 nm just
    after a 500 s scan read as 1.1 nm/s, and relocalisations after it moved the estimate by
    90-260 nm again and again (mixed seed 1; seeds 1-3 filled no slot)."""
    _, _, stat, since = scan.jump_evidence()
    if stat > JUMP_GATE:
        scan.take_jump(since)
    elif scan.stepped:
        scan.drop_jump()


def tear_or_jump(ctx: RunContext, latest, scan_more, take, rows_of):
    """Scanned again latest row first, references fit a jump from one's time and a tear
    between two's rows alike (the same ones carry it), which put the full scan's rows
    differently (mixed seed 1, a tear at 250 s taken for a jump after the scan: the run
    relocalised back and forth by 300 nm). Where a jump after the scan was taken, one more
    reference of the latest rows, scanned after it, carries it or not: looked for where
    each puts it, with no widened search (that took a neighbour for it, mixed seed 10)."""
    scan = ctx.drift.scan
    if not (scan.stepped and scan.tau_jump > scan.tau_end):
        return
    after, tear = scan.tau_jump, scan.jump_evidence(tears_only=True)[3]
    again = _scanned_before(scan, after, ctx.drift.epoch)
    for (kind, rid, seen_t), anew in itertools.chain(((p, False) for p in latest), ((r, True) for r in again)):
        for since in (after, tear) if tear < scan.tau_end else (after,):
            scan.take_jump(since)
            before = len(scan.rows)
            if anew:      # kept apart: its first scan, before the jump, carries none
                scanned = yield from rows_of(ctx, kind, rid, seen_t, widen=False)
                if scanned is not None:
                    take(kind, rid, scanned, key=(kind, rid, "again"))
            else:
                yield from scan_more([(kind, rid, seen_t)], widen=False)
            if len(scan.rows) > before:
                jumped(scan)
                return
    jumped(scan)


def jump_state(scan) -> tuple:
    """Whether a jump is in the model, and from when."""
    return scan.stepped, scan.tau_jump


def told_again(ctx: RunContext, picks, scan_more, take, told: tuple, rows_of):
    """:func:`tear_or_jump` once more where the jump in the model is not what it was
    (``told``, :func:`_jump_state`) when it last ran; the state now."""
    if jump_state(ctx.drift.scan) != told:
        yield from tear_or_jump(ctx, picks.latest(), scan_more, take, rows_of)
    return jump_state(ctx.drift.scan)


def _scanned_before(scan, after: float, ep: float):
    """References of the latest rows scanned again before ``after`` (s after the epoch),
    latest row first, at most :data:`~.bootstrap_picks.TRIES`: where no unscanned pick of
    the latest rows is left, one of these scanned once more tells a jump at ``after`` (it
    now carries it) from a tear (it does not) as well (allpushed seed 8, a tear at 300 s,
    nine particles: taken for a jump after the scan, the four references of the latest
    rows were put 300 nm from where they lay)."""
    for (kind, rid), row in scanned_before(scan, after, bootstrap_picks.TRIES):
        yield kind, rid, row + ep


def narrow_tear(ctx: RunContext, picks, take, rows_of):
    """A tear of the full scan is placed halfway between the rows of the two references
    around it, and the objects on the rows between may lie on its other side, moved by
    the jump where they were not or not where they were (scale300, a tear halfway through
    a 2191 s scan: 1-18 objects 280-315 nm off at the bootstrap's end, seeds 1-10). So
    the particle of those rows nearest halfway with room about it on either side
    (:data:`TEAR_ROOM`) is looked for where each side puts it, with no widened search,
    and the sighting nearer its side's place kept: it halves the rows the tear may lie in.
    Both sides are looked at, since a neighbour, or an object the torn scan did not show,
    can be found where the wrong side puts it (scale300 seed 3: one 45 nm from there, while
    the object lay 5 nm from the other side's place). Up to :data:`TEAR_PROBES` objects, until no unscanned
    particle lies between."""
    scan, ep = ctx.drift.scan, ctx.drift.epoch
    for _ in range(TEAR_PROBES):
        band = tear_band(scan)
        cands = picks.between(band[0] + ep, band[1] + ep) if band else []
        if not cands:
            return
        a, b = band
        room = bootstrap_picks.spots_room(ctx.belief, ctx.refs.first_seen, [c[1] for c in cands], scan.jump)
        mid = 0.5 * (a + b)
        kind, rid, seen_t = pick = min(cands, key=lambda c: (room[c[1]] < TEAR_ROOM, abs(c[2] - ep - mid), c[1]))
        picks.take(pick)
        tau, placed = seen_t - ep, scan.tau_jump
        seen = []
        for since in (0.5 * (a + tau), 0.5 * (tau + b)):     # its row after the tear, before it
            scan.take_jump(since)
            t = yield Msg("clock")
            where = ctx.position(rid) + ctx.offset(t)
            scanned = yield from rows_of(ctx, kind, rid, seen_t, widen=False)
            if scanned is not None:
                seen.append((math.dist(scanned[2][1].at, where), since, scanned))
        scan.take_jump(placed)
        if seen:
            _, since, scanned = min(seen, key=lambda s: s[0])
            scan.take_jump(since)
            take(kind, rid, scanned)
        jumped(scan)
        side = "not found on either side of it" if not seen else \
            f"seen on the rows {'after' if since < tau else 'before'} it"
        yield Msg("event", (f"bootstrap: {rid}, on a row of {seen_t:.0f} s between references' rows of "
                            f"{a + ep:.0f} and {b + ep:.0f} s around the tear, {side}",))
