"""One scan line that checks an after-scan still holds before the next push of its object.

A push of the object the previous push moved may start from that push's after-scan
(``ExecOptions.trust_after_scan``): nothing has touched the object since, and no
measurement has revised the drift estimate. What the estimate cannot know is a jump of
the drift itself since then (a thermal step, a knock), which would send the push to where
the object no longer is. One line settles it at a fraction of a pattern's cost (issue 16:
"one line perpendicular to the coming push may be enough"; Xu, Kalantari and Qian measure
a particle's lateral coordinate so between pushes):

* a **particle**: a line across the coming push through its believed centre. It measures
  the lateral coordinate, the one that decides where the tip meets it; its summit says the
  line passed within ``R/2`` of the centre along the push (:func:`apex`), so a shift along
  the push of more than that is seen too;
* a **rod**: a line along its believed axis, spanning it end to end with ``r_max`` to
  spare. It measures the axial coordinate, which sets where along the rod the push point
  lands; the rod's height along it says the line ran on its crest (a shift across the
  rod of more than about ``d/4`` is seen), and the chord between its crossings that it
  is the rod alone (a neighbour now touching an end lengthens it). A drift jump moves
  the rod without turning it, and nothing else has touched it: a turn is not looked for.

The line either confirms the after-scan, and its coordinate replaces the believed one, or
the push starts with the full ch. 5 pattern as any other (:func:`guard`'s caller).
"""

from __future__ import annotations

import math

import numpy as np

from .context import RunContext
from .engine import Msg
from .rod_scan import is_rod
from .scan_lines import axis, perp
from .scan_steps import one_line

#: How far from the believed centre (along the push, a particle; across the axis, a rod)
#: the line may pass and still confirm the object, as a share of its radius.
PARTICLE_OFF = 0.5
ROD_OFF = 0.5
#: A rod's chord along its axis may differ from its believed length by this share, plus
#: three times the tip radius and 5 nm (the edge level's broadening and the length's own error).
ROD_CHORD = 0.03
#: The angle's 1σ (degrees) a rod's line gives its pivot filter: it measures none.
GUARD_ANGLE_STD = 10.0


def apex(radius: float, tip_radius: float, off: float) -> float:
    """The height a tip of ``tip_radius`` reads passing ``off`` nm from the top of a
    sphere (or, across its axis, a cylinder) of ``radius`` lying on the substrate:
    ``R + √((R + r)² − off²) − r``, 0 beyond reach."""
    reach = radius + tip_radius
    if abs(off) >= reach:
        return 0.0
    return radius + math.sqrt(reach * reach - off * off) - tip_radius


def guard(ctx: RunContext, obj_id: str, heading, tip_radius: float):
    """Check the believed pose of ``obj_id`` with one line before a push heading along
    ``heading`` (layout frame; a rod's line runs along its axis whatever the push). On
    success the measured coordinate replaces the believed one and ``None`` is returned;
    otherwise why not (one short phrase), and the belief is left as it was."""
    o = ctx.belief[obj_id]
    seen = ctx.belief.seen[obj_id]
    t = yield Msg("clock")
    reach = ctx.r_max(t, obj_id)
    centre = np.asarray(o.at, float)
    if o.kind == "rod":
        w = axis(o.angle)
        half = o.length / 2 + reach + ctx.scan_opts.resolved(o.diameter).margin
        out, opts, shift = yield from one_line(ctx, centre, w, half, o.diameter, "guard")
        e = out.edges
        if not e.found:
            return f"the line along it: {e.reason}"
        if not is_rod(out, o.diameter, opts):
            return f"the line along it read {e.peak:.0f} nm, higher than the rod"
        crest = apex(o.diameter / 2, tip_radius, ROD_OFF * o.diameter / 2) - 3.0 * e.noise
        if e.peak < crest:
            return f"the line along it read {e.peak:.0f} nm, off the rod's crest ({crest:.0f} nm)"
        chord = e.right - e.left
        slack = ROD_CHORD * o.length + 3.0 * tip_radius + 5.0
        if abs(chord - o.length) > slack:
            return f"the line along it crossed {chord:.0f} nm of a {o.length:.0f} nm rod"
        along = "along its axis"
    else:
        u = np.asarray(heading, float)
        u = u / max(float(np.linalg.norm(u)), 1e-12)
        w = perp(u)
        half = o.radius + reach + ctx.scan_opts.resolved(o.diameter).margin
        out, opts, shift = yield from one_line(ctx, centre, w, half, o.diameter, "guard")
        e = out.edges
        if not e.found:
            return f"the line across the push: {e.reason}"
        crest = apex(o.radius, tip_radius, PARTICLE_OFF * o.radius) - 3.0 * e.noise
        if e.peak < crest:
            return f"the line across the push read {e.peak:.0f} nm, off its top ({crest:.0f} nm)"
        along = "across the push"
    moved = e.centre - half - shift         # the line's coordinate w, measured less believed
    if abs(moved) > reach:
        return f"its centre {moved:+.0f} nm {along}"
    # the measured coordinate replaces the believed one; the other keeps its variance
    other = perp(w)
    var_other = float(other @ np.asarray(seen.cov, float) @ other)
    t_seen = ctx.scan_ref if ctx.scan_ref is not None else (yield Msg("clock"))
    var_measured = e.centre_std ** 2 + float(w @ ctx.drift.observation_cov(t_seen, np.zeros((2, 2))) @ w)
    new_cov = var_measured * np.outer(w, w) + var_other * np.outer(other, other)
    at = centre + moved * w
    ctx.belief.observe(obj_id, at, t_seen, new_cov, angle=o.angle if o.kind == "rod" else None)
    ctx.refs.raw.discard(obj_id)
    if o.kind == "rod":             # the axial coordinate only: across and the angle as they were
        loose = var_measured * np.outer(w, w) + (o.diameter ** 2) * np.outer(other, other)
        ctx.pivots.seen(ctx.belief[obj_id], loose, angle_std=GUARD_ANGLE_STD)
    yield Msg("event", (f"{obj_id}: its after-scan confirmed by one line ({moved:+.1f} nm)",))
    return None
