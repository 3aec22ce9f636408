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

Between legs, with ``between_legs = "contact"`` (the default), the lateral coordinate comes
from the leg's own forces when they tell it well enough: the contact angle at the leg's end
(:mod:`.contact_angle`) puts the particle at ``r_c`` from the tip's end along the contact
normal, to within :data:`CONTACT_STD` nm (1σ). Before the last leg (but with
``"contact-only"``), and otherwise, a single scan line across the push (sequential
parallel pushing, Xu, Kalantari and Qian) measures it; the longitudinal one is where the
tip stopped, the particle against it. The lateral deviations measure the particle's own
direction error (the same all along one push), and the next legs are aimed to cancel it.

Tracked legs (``"contact"``): the contact angle is read as the tip pushes, chunk by chunk
(:func:`~.motion_steps.stream_push`), and a leg is stopped and the tip lifted once the
particle has slid :data:`TRACK_STOP` of the capture angle round the tip, or once the tip
has gone the model's length with no angle to read. A leg may then run :data:`TRACK_REACH`
times the model's length, and once the particle's turn ``e`` is measured, about the
distance ``r_c sin(α_stop) / tan e`` over which it slides to the stop angle: where the
model must allow three sigmas of an unknown turn, the angle says when it has happened.
A particle steered on its line cannot be held centred on the tip: it moves along the
tip's motion turned by ``e`` and so slides round the tip at ``sin e / r_c`` radians per
nm whatever the tip's heading; the legs re-centre it. Against the simulated physics (a
5 µm push of a particle 5 nm off the believed line, 1.5° of its own turn): 7 legs where
legs of the model's length take 11, within 10 nm of its line; a particle turning 8°
where 2° (1σ) is assumed is stopped on the tip and brought in, where a leg of the
model's length loses it (``tests/test_push_legs.py``).

As the particle slides round the tip it falls behind the tip's end by ``r_c (1 − cos α)``;
each leg is lengthened by what its predicted slide ``α = ℓ sin e / r_c`` costs (4 nm at
the end of a 300 nm leg at 4°).
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.planner import Operation
from nanoasm.planner.plan import Expect

from .context import RunContext
from .engine import Msg
from .monitor import Verdict
from .motion_steps import stream_push
from .reaim import particle_push
from .scan_lines import perp
from .scan_steps import one_line

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
#: Tracked legs (``between_legs = "contact"``): a leg runs up to this many times the
#: model's length (:func:`leg_length`, three sigmas of an unknown turn)...
TRACK_REACH = 3.0
#: ...and is stopped once the contact angle passes this share of the capture angle; once a
#: leg has measured the particle's turn, the next runs this many times the distance over
#: which that turn slides it to the stop angle.
TRACK_STOP = 0.7
TRACK_SLACK = 1.25
#: Legs of one push beyond one per :data:`MIN_LEG` of its length: a bound, never reached
#: by a push that gets on.
MAX_LEGS = 5


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
    half = diameter / 2 + reach + ctx.scan_opts.resolved(diameter).margin
    outcome, _, shift = yield from one_line(ctx, at, perp(np.asarray(u, float)), half, diameter, "SPP")
    if not outcome.edges.found:
        return None
    return outcome.edges.centre - half - shift, outcome.edges.centre_std or 1.0


def _from_contact(contact, tip_end, motion, reach: float, capture_angle: float):
    """The particle's centre (layout nm) and its 1σ from the contact angle at a leg's end,
    the particle ``reach`` nm (radius plus tip radius) from the tip's end ``tip_end`` along
    the contact normal, ``motion`` the tip's direction; None when not measured, not within
    the capture cone, or not to :data:`CONTACT_STD`."""
    if contact is None or abs(contact.angle) >= capture_angle:
        return None
    _, std = contact.lateral(reach)
    if not std <= CONTACT_STD:
        return None
    return _on_tip(tip_end, motion, reach, contact.angle), math.hypot(std, TIP_STD)


def _on_tip(tip_end, motion, reach: float, angle: float):
    """Where a particle sits that touches the tip's end ``tip_end`` at ``angle`` degrees
    round it from the tip's direction ``motion``, its centre ``reach`` nm away."""
    a = math.radians(angle)
    m = np.asarray(motion, float) / np.linalg.norm(motion)
    return np.asarray(tip_end, float) + reach * (math.cos(a) * m + math.sin(a) * perp(m))


def push_in_legs(ctx: RunContext, op: Operation, start, lever, preload: float, tip_radius: float, lead: float):
    """Push a particle from ``start`` (its measured pose) to ``op.expect.at`` in legs,
    located between them (see the module docstring). Returns ``(verdict, legs, the last
    leg's operation)``; the caller scans after the last leg as after any push."""
    opts = ctx.options
    contact = opts.between_legs in ("contact", "contact-only")
    track = TRACK_STOP * opts.capture_angle if contact else None
    goal = np.asarray(op.expect.at, float)
    pos = np.asarray(start.at, float)
    reach_rc = start.radius + tip_radius
    lat_std = math.sqrt(max(float(np.linalg.eigvalsh(ctx.belief.seen[op.object].cov)[-1]), 0.0))
    error, weight = 0.0, 0.0            # the particle's own direction error, degrees, as measured
    legs, verdict, leg_op = 0, None, op
    most = MAX_LEGS + int(float(np.linalg.norm(goal - pos)) / MIN_LEG)
    while legs < most:
        left = float(np.linalg.norm(goal - pos))
        u = (goal - pos) / left
        # once a leg has shown the particle's own turn, that is known to a degree; the
        # particle still slides sideways on the tip at that rate, whatever the aim
        spread = LEARNT_HEADING_STD if weight else opts.push_heading_std
        model = length = leg_length(start.radius, tip_radius, lat_std, spread, opts.capture_angle, error)
        if track is not None:           # the contact angle stops a leg whose particle slides off sooner
            length = TRACK_REACH * model
            if weight:                  # its turn known: it slides to the stop angle over about this
                slide = reach_rc * math.sin(math.radians(track)) / max(abs(math.tan(math.radians(error))), 1e-6)
                length = min(length, max(model, TRACK_SLACK * slide))
        # the last leg, of the model's length, sets where the particle ends: the legs before
        # it leave it that much (the particle's turn over a longer one would land it off its line)
        last = left <= 1.2 * model
        step = left if last else max(min(length, left - model), 0.5 * model)
        heading = _turned(u, -error)     # aimed so the particle's own turn lands it on the line
        # it slides round the tip by step · sin e / r_c as it goes and falls behind the
        # tip's end by r_c (1 - cos) of that: the tip goes on by as much
        slid = min(step * abs(math.sin(math.radians(error))) / reach_rc, math.radians(opts.capture_angle))
        aim = pos + (step + reach_rc * (1.0 - math.cos(slid))) * heading
        leg_lead = max(lead, LEG_LEAD) if contact else lead
        leg_op = particle_push(Operation(op.id, op.object, op.target, op.tip_path, Expect(tuple(aim), None), op.kind),
                               tuple(pos), start.radius, tip_radius, leg_lead)
        if leg_op is None:
            return verdict, legs, op
        # blind beyond the model's own length: no angle to say the particle is still on the tip
        blind = leg_lead + length / TRACK_REACH if track is not None else math.inf
        verdict = yield from stream_push(ctx, leg_op, lever, preload, leg_lead if contact else None, track, blind,
                                         opts.capture_angle)
        legs += 1
        cut = verdict.stopped is not None
        if verdict.failed or (last and not cut):
            return verdict, legs, leg_op
        path = np.asarray(leg_op.tip_path, float)
        motion = path[-1] - path[-2]
        tip_end = np.asarray(verdict.stopped if cut else path[-1], float)
        angle = verdict.contact.angle if verdict.contact is not None \
            and abs(verdict.contact.angle) < opts.capture_angle else 0.0
        expected = _on_tip(tip_end, motion, reach_rc, angle)           # where it sits on the tip
        # the leg that may be the last starts from a line's measurement, but with "contact-only"
        lined = opts.between_legs == "contact" and float(np.linalg.norm(goal - expected)) <= 1.2 * model
        seen = None if not contact or lined else \
            _from_contact(verdict.contact, tip_end, motion, reach_rc, opts.capture_angle)
        how = "its contact angle"
        if seen is None:
            how = "a line across"
            found = yield from across(ctx, expected, heading, 2 * start.radius, 3.0 * max(lat_std, 3.0) + 10.0)
            if found is not None:
                seen = expected + found[0] * perp(heading), found[1]
        if seen is None and not verdict.felt:   # stopped blind, nothing pressing, and not there
            return Verdict("slipped", None, verdict.peak_force), legs, leg_op
        if seen is None:                # off the tip: the scan after the push will look for it
            return verdict, legs, leg_op
        at, std = seen
        lateral, travelled = float((at - pos) @ perp(heading)), float((at - pos) @ heading)
        pos = at
        t = yield Msg("clock")
        ctx.observe(op.object, pos, t, np.eye(2) * std ** 2)
        if travelled >= MIN_LEG / 2:     # the particle's turn off the tip's line
            turn = math.degrees(math.atan2(lateral, travelled))
            error, weight = (error * weight + turn) / (weight + 1.0), weight + 1.0
        lat_std = std
        short = f" stopped short after {travelled:.0f} nm," if cut else ""
        yield Msg("event", (f"{op.object}: leg {legs} of a push,{short} {lateral:+.1f} nm off its line (by {how}); "
                            f"its direction error now {error:+.2f}°",))
        if cut and travelled < MIN_LEG / 2:     # not getting on: the scan after the push takes over
            return verdict, legs, leg_op
    return verdict, legs, leg_op
