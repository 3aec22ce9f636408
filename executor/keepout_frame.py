"""The layout's keep-outs as a witness of the layout frame, where the full scan was torn
before anything the bootstrap scans again.

The layout frame is the scanner's as the full scan began (``FORMATS.md``). The bootstrap
measures the drift that the full scan's rows carried: it scans objects and fixed
features again and compares where they are now with where their rows showed them
(:mod:`.drift_bootstrap`). Those references measure the drift *between* two times, and
the scan's start is one of them only through the references on its first rows.

A jump of the drift while the scan is made, before the row of every reference, is seen
by none of them. Every row after it, and every reference on it, carries the jump. The
rest of the run then works in a frame that lies as far from the layout's as the jump
(allpushed, 300 nm at 150 s of a 600 s scan: seeds 1, 3 and 7, 297-302 nm off; their
check scans found the run's own slots filled).

Where the layout's keep-outs are the outlines of the obstacles the scan shows (electrode
pads drawn where they are), they still tell where the scan's start lies. So their
corners are registered to the obstacles' corners (:func:`~nanoasm.planner.alignment.register`,
as marks are, each obstacle corner put back by its row's drift as the bootstrap's model
now has it). Where the keep-outs lie more than :data:`FRAME_GATE` times the layout's
position tolerance from the obstacles, each matched corner becomes a reference of the
model: its image position less the keep-out's corner is the drift ``D(τ) − D(0)`` of its
row ``τ`` since the scan began. The bootstrap's jump test
(:func:`~.scan_jump.evidence`) then weighs a tear before their rows against the others,
as it weighs any reference.

A tear within the obstacles' own rows moves their later corners and not the earlier
ones: the keep-outs then fit the obstacles as well at two places, and the registration
fails as ambiguous (:class:`~nanoasm.planner.alignment.AmbiguousMatch`). Two such fits
that share no corner, whose rows lie one side and the other, and whose corners come in
the same order in both (:func:`torn_sides`), are read as the two sides of a tear, and
the corners of both become references (allpushed seed 1, 300 nm at 300 s between the
electrodes' lower and upper corners, with no reference before it: the estimate was 303
nm off, now 2.2 nm).

Where the keep-outs agree with the obstacles, or are not their outlines (no registration
of at least three corners within the layout's tolerance, nor two sides of a tear), or the
layout has marks (it is registered to them instead), or ``--no-align`` was given, nothing
is added.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from nanoasm.cad.layout import Layout
from nanoasm.errors import InputError
from nanoasm.planner.alignment import AmbiguousMatch, register

from .engine import Msg

#: The keep-outs are taken as witnesses once the obstacles lie further than this many
#: times the layout's position tolerance from them on average: a frame that far off
#: leaves every slot missed however well it is filled.
FRAME_GATE = 3.0
#: Largest rotation (degrees) of the keep-outs against the obstacles for them to witness
#: a shift of the frame (a jump moves, it does not turn).
MAX_TURN = 1.0
#: Least standard deviation (nm) of a matched corner's components: the identified outline
#: is the full scan's, at its pixels, rounded by the tip.
CORNER_STD = 10.0
#: Corners of two registrations this close (nm) are the same corner.
SAME_CORNER = 20.0


@dataclass(frozen=True)
class KeepoutWitness:
    """What :func:`witness` needs of the run: the layout (in the scan's frame: without
    marks; its area is the scan's), the obstacles the full scan showed, when a full-scan
    height ``y`` (nm) was scanned (``row_time``, instrument s) and the scan's pixel size (nm)."""

    layout: Layout
    obstacles: tuple
    row_time: object
    resolution: float

    def pairs(self, scan, epoch: float):
        """The keep-outs registered to the obstacles, each obstacle corner put back by
        ``scan``'s drift of its row (τ: s after ``epoch``): a list of ``(transform,
        [(keep-out corner, obstacle corner put back, image corner, τ)])``, one for the
        registration, or one for each side of a tear (:func:`torn_sides`), each
        :func:`_usable`; None where they do not register so."""
        from nanoasm.world.environment import Environment

        raw = {}

        def moved(p):
            tau = self.row_time(p[1]) - epoch
            q = np.asarray(p, float) - scan.offset(tau)
            raw[(round(float(q[0]), 6), round(float(q[1]), 6))] = (tuple(map(float, p)), tau)
            return float(q[0]), float(q[1])

        probe = replace(self.layout, keepouts=(), marks=self.layout.keepouts)
        env = Environment(self.layout.area, (), tuple(self.obstacles), None)
        try:
            fits = (register(probe, env, resolution=self.resolution, moved=moved),)
        except AmbiguousMatch as err:
            fits = err.fits
        except InputError:
            return None

        def seen(al):
            out = []
            for mark, found in al.pairs:
                got = raw.get((round(found[0], 6), round(found[1], 6)))
                if got is not None:
                    out.append((mark, found, *got))
            return al.transform, out

        groups = [seen(al) for al in fits]
        if len(groups) > 1:
            return torn_sides(groups)
        return groups if _usable(*groups[0]) else None


def _usable(transform, pairs) -> bool:
    """Whether a registration may witness a shift of the frame: at least three corners
    found again, turned by at most :data:`MAX_TURN`."""
    return len(pairs) >= 3 and abs(transform.rotation) <= MAX_TURN


def torn_sides(groups):
    """Rival registrations read as the two sides of a tear, ordered by row, or None.

    Two of them are sides of a tear when each is :func:`_usable`, they match no keep-out
    corner and no obstacle corner in common (within :data:`SAME_CORNER`), the rows of one
    all come before the rows of the other,
    and their keep-out corners come in the same order along the slow axis as their
    obstacle corners (a jump moves every row after it alike; a repeated outline matched to
    its twin crosses them). Of several such pairs, the one whose sides lie nearest each
    other (the smallest jump)."""
    best, groups = None, [g for g in groups if _usable(*g)]
    for i, (ta, a) in enumerate(groups):
        for tb, b in groups[i + 1:]:
            if _shared(a, b):
                continue
            (t0, early), (t1, late) = sorted(((ta, a), (tb, b)), key=lambda tg: min(p[3] for p in tg[1]))
            if max(p[3] for p in early) >= min(p[3] for p in late):
                continue
            if (max(p[0][1] for p in early) - min(p[0][1] for p in late)) * (
                    max(p[1][1] for p in early) - min(p[1][1] for p in late)) <= 0:
                continue
            jump = math.dist(t0.translation, t1.translation)
            if best is None or jump < best[0]:
                best = (jump, [(t0, early), (t1, late)])
    return None if best is None else best[1]


def _shared(a, b) -> bool:
    """Whether two registrations' pairs share a keep-out corner (each fit grows them by
    its own broadening) or an obstacle corner."""
    for i in (0, 1):
        pa, pb = (np.array([p[i] for p in g], float) for g in (a, b))
        if np.hypot(*(pa[:, None, :] - pb[None, :, :]).transpose(2, 0, 1)).min() <= SAME_CORNER:
            return True
    return False


def witness(ctx, keep: KeepoutWitness | None, jumped):
    """Add the keep-outs' corners to the bootstrap's model as references of the drift
    since the scan began where they lie far from the obstacles as the model places them
    (see the module's docstring); then ``jumped(scan)`` places a jump again. Returns
    whether they were added."""
    if keep is None or not keep.layout.keepouts:
        return False
    drift = ctx.drift
    scan, ep = drift.scan, drift.epoch
    groups = keep.pairs(scan, ep)
    if groups is None:
        return False
    means = [np.mean([np.subtract(found, mark) for mark, found, _, _ in pairs], axis=0) for _, pairs in groups]
    gate = FRAME_GATE * keep.layout.tolerance.position
    far = max(range(len(means)), key=lambda i: math.hypot(*means[i]))
    if math.hypot(*means[far]) <= gate:
        return False
    k = 0
    for transform, pairs in groups:
        var = max(CORNER_STD, transform.residual) ** 2
        for mark, _, img, tau in pairs:
            k += 1
            d = np.asarray(img) - np.asarray(mark) - scan.creep_at(tau)
            for n in ((1.0, 0.0), (0.0, 1.0)):
                scan.measure(np.array(n), float(np.dot(n, d)), tau, 0.0, var, key=("keepout", f"k{k}"))
    jumped(scan)
    mean, corners = means[far], sum(len(pairs) for _, pairs in groups)
    torn = "" if len(groups) == 1 else (
        f" (their corners on rows scanned before {min(p[3] for p in groups[1][1]) + ep:.0f} s register apart "
        f"from the later ones, {math.hypot(*np.subtract(means[1], means[0])):.0f} nm apart: the scan torn between)")
    yield Msg("event", (f"the layout's keep-outs lie {mean[0]:+.0f}, {mean[1]:+.0f} nm from the obstacles the full "
                        f"scan shows, as the drift references place them ({corners} corners; more than "
                        f"{gate:g} nm){torn}: their corners taken as references of the drift since the scan began, "
                        f"a tear of the scan before the references' rows weighed",), {"level": "warn"})
    return True
