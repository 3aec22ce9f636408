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

Where the keep-outs agree with the obstacles, or are not their outlines (no registration
of at least three corners within the layout's tolerance), or the layout has marks (it is
registered to them instead), or ``--no-align`` was given, nothing is added.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from nanoasm.cad.layout import Layout
from nanoasm.errors import InputError
from nanoasm.planner.alignment import register

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
        """``(transform, [(keep-out corner, obstacle corner put back, image corner, τ)])``:
        the keep-outs registered to the obstacles with each obstacle corner put back by
        ``scan``'s drift of its row (τ: s after ``epoch``); None where they do not register."""
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
            al = register(probe, env, resolution=self.resolution, moved=moved)
        except InputError:
            return None
        out = []
        for mark, found in al.pairs:
            seen = raw.get((round(found[0], 6), round(found[1], 6)))
            if seen is not None:
                out.append((mark, found, *seen))
        return al.transform, out


def witness(ctx, keep: KeepoutWitness | None, jumped):
    """Add the keep-outs' corners to the bootstrap's model as references of the drift
    since the scan began where they lie far from the obstacles as the model places them
    (see the module's docstring); then ``jumped(scan)`` places a jump again. Returns
    whether they were added."""
    if keep is None or not keep.layout.keepouts:
        return False
    drift = ctx.drift
    scan, ep = drift.scan, drift.epoch
    got = keep.pairs(scan, ep)
    if got is None:
        return False
    transform, pairs = got
    if len(pairs) < 3 or abs(transform.rotation) > MAX_TURN:
        return False
    mean = np.mean([np.subtract(found, mark) for mark, found, _, _ in pairs], axis=0)
    gate = FRAME_GATE * keep.layout.tolerance.position
    if math.hypot(*mean) <= gate:
        return False
    var = max(CORNER_STD, transform.residual) ** 2
    for k, (mark, _, img, tau) in enumerate(pairs):
        d = np.asarray(img) - np.asarray(mark) - scan.creep_at(tau)
        for n in ((1.0, 0.0), (0.0, 1.0)):
            scan.measure(np.array(n), float(np.dot(n, d)), tau, 0.0, var, key=("keepout", f"k{k + 1}"))
    jumped(scan)
    yield Msg("event", (f"the layout's keep-outs lie {mean[0]:+.0f}, {mean[1]:+.0f} nm from the obstacles the full "
                        f"scan shows, as the drift references place them ({len(pairs)} corners; more than "
                        f"{gate:g} nm): their corners taken as references of the drift since the scan began, "
                        f"a tear of the scan before the references' rows weighed",), {"level": "warn"})
    return True
