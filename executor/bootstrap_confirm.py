"""A bootstrap reference that only a widened search found, confirmed or refuted by a second
object before it measures the drift (:func:`confirm`).

A widened search takes whatever particle lies nearest where it looked. After a drift jump
as the full scan ends, the first references are each hundreds of nm from where the model
puts them, and a search finds another particle for one as often as not: on allpushed seed 1
with a 300 nm jump at the scan's end (d480fe9), the two first references measured the
drift 405 and 696 nm off, and every reference after them, looked for where those put the
drift, needed a widened search too; the run filled one of nine slots. So what such a
search found is a hypothesis: the sample moved by ``Δ`` (where it was seen, less where it
was believed). Every other object then lies ``Δ`` from where it is believed too, give or
take the velocity's error over the rows between; a particle of the nearest rows, looked
for there with the lines the model sizes and no search, is found (the hypothesis holds:
both measure the drift) or not (it does not: neither does). Random sample consensus with
the least sample, two.
"""

from __future__ import annotations

import numpy as np

from .context import RunContext
from .engine import Msg

#: Particles of the nearest rows tried, each looked for where the hypothesis puts it.
CONFIRM_TRIES = 2


def candidates(picks, seen_t: float, rid: str) -> list:
    """Unscanned particles (picks), nearest ``seen_t`` in the full scan's rows first."""
    out = [p for s in picks.stretches for p in s if p[0] == "object" and p[1] != rid]
    return sorted(out, key=lambda p: (abs(p[2] - seen_t), p[1]))[:CONFIRM_TRIES]


def confirm(ctx: RunContext, picks, rid: str, seen_t: float, scanned, rows_of):
    """Whether the reference ``rid`` (seen in the full scan at ``seen_t``), which only a
    widened search found (``scanned``: what ``rows_of`` returned for it), is confirmed
    (plan stub). Returns ``(pick, its scanned)`` of the particle that confirmed it, None
    when none was found where the hypothesis puts it, or ``()`` when there is none to try.
    ``rows_of``: the bootstrap's ``(ctx, kind, id, seen_t, widen, searched, shift)`` scan."""
    _, t, seen = scanned
    body = seen[1]
    shift = ctx.to_layout(body, t).at - ctx.position(rid)
    tries = candidates(picks, seen_t, rid)
    if not tries:
        return ()
    for pick in tries:
        other = yield from rows_of(ctx, pick[0], pick[1], pick[2], False, None, shift)
        if other is not None:
            yield Msg("event", (f"bootstrap: what a widened search took for {rid} ({np.hypot(*shift):.0f} nm "
                                f"from where it was believed) is confirmed by {pick[1]}, found that far from its "
                                f"place too",))
            return pick, other
    yield Msg("event", (f"bootstrap: what a widened search took for {rid} is not confirmed: "
                        f"{', '.join(p[1] for p in tries)} not where it would put them; not a reference",),
              {"level": "warn"})
    return None
