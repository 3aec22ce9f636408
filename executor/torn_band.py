"""The band of the sample a drift jump during the full scan left unimaged (plan stub).

The full scan's rows are acquired bottom to top. Where the drift jumps between two rows by
``J`` (the bootstrap takes such a tear into its model, :mod:`.scan_jump`), the row after the
jump images the sample ``-J_y`` further on than the row before it would have: with ``J_y <
0`` a band of the sample ``|J_y|`` high is never imaged, and an object lying in it is
never identified (with ``J_y > 0`` a band is imaged twice, :mod:`.tear_doubles`). A layout
needing every particle then leaves a slot unassigned (allpushed seeds 3 and 5 with 300 nm
at 300 s: 8 of 9 slots, the ninth particle in the band).

When the belief holds fewer particles than the layout has particle slots, that band, a
particle's radius beyond it, is surveyed before the first plan: square windows along it
(:func:`.repair.tiles`), each imaged and matched to the belief as a repair round's survey
is (:func:`.repair.survey_window`), a particle seen where nothing is believed added; the
windows nearest the jump's row in the model first, coarser than the full scan, and no more
once the particles are as many as the slots.
"""

from __future__ import annotations

import numpy as np
import shapely

from .context import RunContext
from .engine import Msg
from .repair import spare_particles, survey_window, tiles
from .scan_jump import tear_band

#: Beyond the band (nm): a particle whose centre lies within this of it reaches into it.
BAND_MARGIN = 60.0
#: A band narrower than this many of the full scan's pixels hides nothing.
LEAST_PIXELS = 2.0
#: The survey's pixels: this many across the smallest particle seen (identification needs
#: a few pixels of an object; 80 nm particles at the full scan's 10 nm are 8 across).
PIXELS_ACROSS = 3.0


def skipped_band(ctx: RunContext, t0: float, line_time: float, pixels: int, side: float):
    """``(y0, y1)``: the layout rows (nm) the full scan may have skipped where the drift
    jumped during it, as the bootstrap's model has it; None without such a jump, or where
    it skipped less than :data:`LEAST_PIXELS`. The jump lies between the rows of the
    references either side of it (:func:`.scan_jump.tear_band`): the band reaches from the
    first of those rows to the second (allpushed seed 3, 300 nm at 300 s: the model put the
    jump at 323 s, and the particle never imaged lay 200 nm below the band of that row).
    The full scan began at ``t0``, a row every ``line_time`` s, ``pixels`` rows over
    ``side`` nm."""
    drift = ctx.drift
    scan = getattr(drift, "scan", None)
    if scan is None or not scan.stepped or scan.tau_end is None or not scan.tau_jump < scan.tau_end:
        return None

    def layout_y(tau: float) -> float:
        return _layout_row(ctx, tau, t0, line_time, pixels, side)

    tau = scan.tau_jump
    if layout_y(tau) - layout_y(tau - 1e-6) < LEAST_PIXELS * side / pixels:
        return None                             # rows imaged twice, or too few skipped
    between = tear_band(scan) or (tau, tau)
    return layout_y(min(between[0], tau - 1e-6)), layout_y(max(between[1], tau))


def _layout_row(ctx: RunContext, tau: float, t0: float, line_time: float, pixels: int, side: float) -> float:
    """The layout row (nm) the full scan's row at ``tau`` (s after the epoch) imaged, by the
    drift model (its jump included from the jump's time on)."""
    drift = ctx.drift
    row = min(max((tau + drift.epoch - t0) / line_time - 0.5, 0.0), pixels - 1.0)
    return float(drift.unskew(np.array([0.5 * side, row * side / pixels]), tau)[1])


def survey_band(ctx: RunContext, layout, t0: float, line_time: float, pixels: int, side: float, tip_radius: float):
    """Survey the band :func:`skipped_band` finds, if the belief holds fewer particles than
    ``layout`` has particle slots (plan stub): the windows nearest the row the model puts
    the jump at first, at pixels a third of the smallest particle's diameter (at least the
    full scan's), until the particles are as many as the slots."""
    band = skipped_band(ctx, t0, line_time, pixels, side)
    if band is None:
        return
    slots = sum(t.kind == "particle" for t in layout.targets)
    seen = spare_particles(ctx)
    if not seen or seen >= slots:
        return
    y0, y1 = band
    windows = tiles(shapely.box(0.0, y0, side, y1), margin=BAND_MARGIN)
    middle = _layout_row(ctx, ctx.drift.scan.tau_jump, t0, line_time, pixels, side)
    windows.sort(key=lambda w: (abs(0.5 * (w[1] + w[3]) - middle), w[0]))
    smallest = min(o.diameter for o in ctx.belief.objects.values() if o.kind == "particle")
    pixel = max(side / pixels, smallest / PIXELS_ACROSS)
    yield Msg("event", (f"the full scan may have skipped rows within {y0:.0f}-{y1:.0f} nm where the drift "
                        f"jumped, and {seen} particle(s) are seen for {slots} slot(s): surveying them "
                        f"({len(windows)} window(s) at most, {pixel:.0f} nm pixels)",), {"level": "warn"})
    before = set(ctx.belief.objects)
    for k, window in enumerate(windows):
        yield from survey_window(ctx, window, k + 1, tip_radius, pixel=pixel)
        if spare_particles(ctx) >= slots:
            break
    new = sorted(set(ctx.belief.objects) - before)
    if new:
        yield Msg("event", (f"in the skipped rows: {', '.join(new)}",))
