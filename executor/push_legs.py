"""Long particle pushes in legs, each no longer than the object stays on the tip's line.

A pushed particle does not move exactly along the tip's motion: its own direction
scatters by a few degrees (``push_heading_std``, friction differing across its contact).
The tip carries it only while the contact normal lies within the capture cone about its
motion (``capture_angle``, half-angle); the particle drifts sideways at ``tan e`` per
nm pushed, so it slides off once its lateral offset reaches ``(R + r_tip) sin α_c``.

The model (:func:`leg_length`): with the particle's lateral position known to
``σ_lat`` at the start of a leg, a leg of length ``ℓ`` keeps it captured at three
sigmas while ``3 √(σ_lat² + (ℓ tan σ_e)²) ≤ (R + r_tip) sin α_c``. For a 90 nm particle
and a 10 nm tip (39 nm of capture), σ_e = 2° and σ_lat = 3 nm: legs of 360 nm, where a
single push goes astray beyond a micrometre (issue 13's measurement: half of the 1-2 µm
pushes ended more than 100 nm off course). Against the simulated physics (the same
particle pushed 3 µm with its direction error set to 1, 2, 4 and 6°) the release
distance ``(R + r_tip) sin α_c / tan e`` came within 2 % of where the particle was
dropped (``tests/test_push_legs.py``). Once a leg has measured the particle's own turn
``e``, the legs are cut to ``ℓ |tan e| + 3 √(σ_lat² + (ℓ tan 1°)²) ≤ (R + r_tip) sin α_c``.

Between legs, with ``between_legs = "contact"`` (the default), the lateral coordinate comes from
the leg's own forces when they tell it well enough: the contact angle at the leg's end (:mod:`.contact_angle`) puts the
particle at ``r_c`` from the tip's end along the contact normal, to within
:data:`CONTACT_STD` nm (1σ). Before the last leg, and otherwise, a single scan line across the push (sequential
parallel pushing, Xu, Kalantari and Qian) measures it; the longitudinal one is where the
tip stopped, the particle against it. The lateral deviations measure the particle's own
direction error (the same all along one push), and the next legs are aimed to cancel it.
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.planner import Operation
from nanoasm.planner.plan import Expect

from .context import RunContext
from .engine import Msg
from .motion_steps import stream_push
from .reaim import particle_push
from .scan_lines import make_line, measure_line, perp
from .scan_steps import run_pattern

#: Least leg (nm): shorter than this, the scans between legs would cost more than they save.
MIN_LEG = 100.0
#: Uncertainty (degrees) of a particle's direction error once a leg has measured it.
LEARNT_HEADING_STD = 1.0
#: Largest 1σ (nm) of a particle's place from the contact angle for it to stand in for a line.
CONTACT_STD = 2.0
#: The tip's own place at a leg's end, 1σ (nm): the DAC's following of the path, drift, the
#: lever's calibration (in one traced run, allpushed seed 1, 41 legs, the contact angle's
#: places lay within 7 nm of the truth across the push, most within 4, where its own σ
#: said 1-2 nm).
TIP_STD = 3.0
#: Least lead (nm) of a leg after the first: the particle's place along the push is known
#: worst (10-20 nm), and the contact angle needs the tip to slide before it meets it.
LEG_LEAD = 40.0


def leg_length(radius: float, tip_radius: float, lateral_std: float, heading_std: float,
               capture_angle: float, known: float = 0.0) -> float:
    """The longest leg (nm) that keeps a particle of ``radius`` on a tip of ``tip_radius``
    at three sigmas: ``ℓ |tan e| + 3 √(σ_lat² + (ℓ tan σ_e)²) ≤ (R + r_tip) sin α_c``,
    ``e`` the particle's direction error as measured so far (``known``, degrees; 0 before
    the first leg) and ``σ_e`` its uncertainty (``heading_std``); ``lateral_std`` nm."""
    capture = (radius + tip_radius) * math.sin(math.radians(capture_angle))
    drift = abs(math.tan(math.radians(known)))
    spread = math.tan(math.radians(max(heading_std, 1e-3)))

    def fits(ell: float) -> bool:
        return ell * drift + 3.0 * math.hypot(lateral_std, ell * spread) <= capture

    if not fits(0.0):
        return MIN_LEG
    lo, hi = 0.0, capture / max(drift, 1e-6)
    for _ in range(60):                        # bisection: the left side grows with ℓ
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return max(lo, MIN_LEG)


def _turned(u: np.ndarray, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]])


def across(ctx: RunContext, at, u, diameter: float, reach: float):
    """One scan line across a particle expected at ``at`` (layout frame), perpendicular to
    the push direction ``u``: its lateral coordinate (nm along ``perp(u)`` from ``at``)
    and that coordinate's 1σ, or None when the line finds nothing."""
    t = yield Msg("clock")
    v = perp(np.asarray(u, float))
    opts = ctx.scan_opts.resolved(diameter)
    half = diameter / 2 + reach + opts.margin
    line = make_line(np.asarray(at, float) + ctx.offset(t), v, -half, half, opts.spacing, "SPP")

    def pattern():
        outcome = yield from measure_line(line, half, opts)
        return outcome

    outcome = yield from run_pattern(ctx, pattern())
    if not outcome.edges.found:
        return None
    t_scan = ctx.scan_ref if ctx.scan_ref is not None else t
    shift = ctx.offset(t_scan) - ctx.offset(t)       # the line was placed at t's offset
    lateral = outcome.edges.centre - half - float(shift @ v)
    return lateral, outcome.edges.centre_std or 1.0


def _from_contact(contact, leg_op: Operation, aim, u, reach: float, capture_angle: float):
    """The particle's lateral coordinate (nm along ``perp(u)`` from ``aim``) and its 1σ
    from the contact angle at the leg's end, the particle ``reach`` nm (radius plus tip
    radius) from the tip's end along the contact normal; None when not measured, not
    within the capture cone, or not to :data:`CONTACT_STD`."""
    if contact is None or abs(contact.angle) >= capture_angle:
        return None
    _, std = contact.lateral(reach)
    if not std <= CONTACT_STD:
        return None
    path = np.asarray(leg_op.tip_path, float)
    m = (path[-1] - path[-2]) / np.linalg.norm(path[-1] - path[-2])
    a = math.radians(contact.angle)
    particle = path[-1] + reach * (math.cos(a) * m + math.sin(a) * perp(m))
    return float((particle - np.asarray(aim, float)) @ perp(np.asarray(u, float))), math.hypot(std, TIP_STD)


def push_in_legs(ctx: RunContext, op: Operation, start, lever, preload: float, tip_radius: float, lead: float):
    """Push a particle from ``start`` (its measured pose) to ``op.expect.at`` in legs,
    one line across between them (see the module docstring). Returns ``(verdict, legs,
    the last leg's operation)``; the caller scans after the last leg as after any push."""
    opts = ctx.options
    goal = np.asarray(op.expect.at, float)
    pos = np.asarray(start.at, float)
    lat_std = math.sqrt(max(float(np.linalg.eigvalsh(ctx.belief.seen[op.object].cov)[-1]), 0.0))
    error, weight = 0.0, 0.0            # the particle's own direction error, degrees, as measured
    legs, verdict, leg_op = 0, None, op
    while True:
        left = float(np.linalg.norm(goal - pos))
        u = (goal - pos) / left
        # once a leg has shown the particle's own turn, that is known to a degree; the
        # particle still slides sideways on the tip at that rate, whatever the aim
        spread = LEARNT_HEADING_STD if weight else opts.push_heading_std
        length = leg_length(start.radius, tip_radius, lat_std, spread, opts.capture_angle, error)
        last = left <= 1.2 * length
        step = left if last else length
        aim = pos + step * _turned(u, -error)      # aimed so the particle's own turn lands it on the line
        leg_lead = lead if legs == 0 or opts.between_legs != "contact" else max(lead, LEG_LEAD)
        leg_op = particle_push(Operation(op.id, op.object, op.target, op.tip_path, Expect(tuple(aim), None), op.kind),
                               tuple(pos), start.radius, tip_radius, leg_lead)
        if leg_op is None:
            return verdict, legs, op
        verdict = yield from stream_push(ctx, leg_op, lever, preload, None if last or opts.between_legs != "contact" else leg_lead)
        legs += 1
        if last or verdict.failed:
            return verdict, legs, leg_op
        # the last leg sets where the particle ends: it starts from a line's measurement
        seen = None if opts.between_legs != "contact" or float(np.linalg.norm(goal - aim)) <= 1.2 * length else \
            _from_contact(verdict.contact, leg_op, aim, _turned(u, -error), start.radius + tip_radius,
                          opts.capture_angle)
        how = "its contact angle"
        if seen is None:
            how = "a line across"
            seen = yield from across(ctx, aim, _turned(u, -error), 2 * start.radius,
                                     3.0 * max(lat_std, 3.0) + 10.0)
        if seen is None:                # off the tip: the scan after the push will look for it
            return verdict, legs, leg_op
        lateral, std = seen
        t = yield Msg("clock")
        pos = aim + lateral * perp(_turned(u, -error))
        ctx.observe(op.object, pos, t, np.eye(2) * std ** 2)
        turn = math.degrees(math.atan2(lateral, step))      # the particle's turn off the tip's line
        error, weight = (error * weight + turn) / (weight + 1.0), weight + 1.0
        lat_std = std
        yield Msg("event", (f"{op.object}: leg {legs} of a push, {lateral:+.1f} nm off its line (by {how}); "
                            f"its direction error now {error:+.2f}°",))
