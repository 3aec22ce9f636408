"""Objects a tear of the full scan imaged twice (:func:`doubles`).

A jump of the drift while the full scan is made tears it (:mod:`.scan_jump`); where the
jump moves the sample back along the slow axis, the rows after the tear scan a band of
it again, |J_y| wide, and what lay there is identified twice: two objects to the
belief, one on the rows before the tear and one on the rows after it, which with the
jump taken out lie at the same place. Looked for there, each is found where both are,
so the sighting is ambiguous and neither is found (``scale300`` seed 8, 300 nm at 1096 s
of a 2191 s scan: the three particles nearest the tear, each with a double within 3 nm
of the same true object)."""

from __future__ import annotations

import math

import numpy as np

from .scan_jump import tear_band

#: Centres (nm) closer than this, with the jump taken out, are one object imaged twice:
#: a located centre errs by a few nm and the jump's estimate by about 5; two objects
#: this close would overlap.
DOUBLE_GATE = 20.0
#: Largest relative difference of size (and a rod's length) between the two images.
DOUBLE_SIZE = 0.2
#: Largest difference (°) of a rod's angle between the two images.
DOUBLE_ANGLE = 10.0


def doubles(ctx) -> list[tuple[str, str, float]]:
    """``(first, again, distance)`` for each object ``first`` on rows before a tear that
    ``again``, on the rows after it, images once more: the rows scanned again hold
    the two, one before the references' band around the tear (its rows ``(a, b)``) by at
    most the jump's slow-axis part, one after; with the jump taken out of the later one
    (and neither's row drift) they lie within :data:`DOUBLE_GATE` of each other and are
    of like kind and size. Empty without a tear, or where the jump skipped a band."""
    drift = ctx.drift
    scan = drift.scan
    band = tear_band(scan)
    first = {oid: v for oid, v in ctx.refs.first_seen.items() if oid in ctx.belief.objects}
    if band is None or len(first) < 2:
        return []
    rows, image = ctx.landmarks.rows, ctx.full_scan
    if rows is None or image is None or scan.jump[1] <= 0.0:
        return []                                      # rows go up in y: a band skipped, none twice
    ep = drift.epoch
    ids = sorted(first)
    tau = np.array([first[oid][1] - ep for oid in ids], float)
    per_nm = rows[1] / image.pixel_size                # s of rows per nm along the slow axis
    again = scan.jump[1] * per_nm                      # s of rows the jump scanned again
    a, b = band
    size = max(ctx.belief[oid].diameter for oid in ids) * per_nm
    before = [i for i in range(len(ids)) if a - again - size <= tau[i] < b]
    after = [i for i in range(len(ids)) if a < tau[i] <= b + again + size]
    if not before or not after:
        return []
    # each position with its row's drift taken out, the jump left in
    placed = {i: drift.unskew(np.asarray(first[ids[i]][0], float), tau[i]) + scan.step(tau[i])
              for i in set(before) | set(after)}
    out, taken = [], set()
    for j in sorted(after, key=lambda j: tau[j]):
        if j in taken:
            continue
        later = placed[j] - scan.jump
        near = [(float(math.dist(placed[i], later)), i) for i in before
                if tau[i] < tau[j] and i not in taken and _alike(ctx.belief[ids[i]], ctx.belief[ids[j]])]
        d, i = min(near, default=(math.inf, -1))
        if d <= DOUBLE_GATE:
            taken.update((i, j))
            out.append((ids[i], ids[j], d))
    return out


def _alike(p, q) -> bool:
    """Of one kind and like size (a rod's length and angle too)."""
    if p.kind != q.kind or abs(p.diameter - q.diameter) > DOUBLE_SIZE * max(p.diameter, q.diameter):
        return False
    if p.kind != "rod":
        return True
    turn = abs((p.angle - q.angle + 90.0) % 180.0 - 90.0)
    return abs(p.length - q.length) <= DOUBLE_SIZE * max(p.length, q.length) and turn <= DOUBLE_ANGLE
