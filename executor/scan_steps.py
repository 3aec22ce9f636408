"""Local scans as plan stubs: patterns run through scan_line messages, the scans before and
after a push, and the widening search for an object that is not where it should be.

Free generator functions over a :class:`~nanoasm.executor.context.RunContext`: each
yields :class:`~nanoasm.executor.engine.Msg` objects and returns its result, as bluesky's
plan stubs do.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from nanoasm.bodies import Body
from nanoasm.planner import Operation

from .context import RunContext
from .engine import Msg
from .association import Candidate, associate, sighting
from .progress_docs import PROGRESS, ProgressDoc
from .apex_check import CROWDED, ROUND, apex_cov, image_check
from .local_scan import particle_after, particle_after_predicted, particle_before, rod_after, rod_before
from .scan_lines import LocalScanResult, make_line, measure_line
from .lost_search import find_lost_particle
from .rod_predicted import rod_after_predicted
from .motion_steps import approach

#: Covariance (nm²) of a located centre when the pattern gives none.
DEFAULT_COV = 4.0


def run_pattern(ctx: RunContext, pattern, what: str | None = None):
    """Run a local-scan pattern (a generator of lines, sent each line's profile) through
    scan_line messages; returns its result. The travels to the lines count as travel.
    ``what``: the scan's name in its progress line."""
    led = ctx.ledger
    t0 = yield Msg("clock")
    travel0, switch0 = led.times["travel"], led.times["mode_switch"]
    led.counts["local_scans"] += 1
    ctx.scan_ref = None
    ctx.scan_comp = np.zeros((2, 2))
    ctx.scan_creep = []
    lines = 0
    try:
        line = next(pattern)
        while True:
            profile = yield from scan_line(ctx, np.asarray(line.a, float), np.asarray(line.b, float), int(line.n))
            lines += 1
            line = pattern.send(profile)
    except StopIteration as stop:
        result = stop.value
    if getattr(result, "cov", None) is not None:     # what the lines' compensation may err by
        result = replace(result, cov=np.asarray(result.cov, float) + ctx.scan_comp)
    if hasattr(result, "line_creep") and ctx.scan_creep:
        result = replace(result, line_creep=np.array(ctx.scan_creep, float).reshape(-1, 2))
    t1 = yield Msg("clock")
    scanning = t1 - t0 - (led.times["travel"] - travel0) - (led.times["mode_switch"] - switch0)
    led.times["local_scan"] += scanning
    said = f"{what}, " if what else ""
    yield Msg("emit", (PROGRESS, ProgressDoc("local scan", f"{said}{lines} line(s), {scanning:.1f} s")))
    return result


def one_line(ctx: RunContext, centre, direction, half: float, diameter: float, role: str):
    """One scan line, a local scan of its own, through ``centre`` (layout nm) along
    ``direction``, ``half`` nm to each side, for an object of ``diameter``. Returns its
    outcome, the resolved scan options, and how far (nm, along ``direction``) the drift
    estimate moved the sample between placing the line and scanning it (subtract it from
    a position read on the line)."""
    t = yield Msg("clock")
    opts = ctx.scan_opts.resolved(diameter)
    u = np.asarray(direction, float)
    line = make_line(np.asarray(centre, float) + ctx.offset(t), u, -half, half, opts.spacing, role)

    def pattern():
        outcome = yield from measure_line(line, half, opts)
        return outcome

    outcome = yield from run_pattern(ctx, pattern())
    t_scan = ctx.scan_ref if ctx.scan_ref is not None else t
    return outcome, opts, float((ctx.offset(t_scan) - ctx.offset(t)) @ u)


def scan_line(ctx: RunContext, a: np.ndarray, b: np.ndarray, n: int):
    """A scan line, cut to the scanner's range: samples beyond it read as bare substrate
    (the median of the rest), so a pattern near the range's edge still works.

    The lines of one pattern are drift-compensated: each is shifted by the offset
    predicted since the pattern's first line (``ctx.scan_ref``: when it began scanning,
    after the switch back to tapping a push leaves it to wait for, 2 s in which the sample
    drifts and creeps on), so the pattern sees the sample as it lay then, however fast
    creep moves it after a travel, and its result
    is converted with the offset of that time. What that shift may err by is kept in
    ``ctx.scan_comp`` (the worst line's) and added to the pattern's result."""
    yield from approach(ctx, a)
    t_line = yield Msg("clock")
    first = ctx.scan_ref is None
    if first:
        ctx.scan_ref = t_line
    shift = ctx.offset(t_line) - ctx.offset(ctx.scan_ref)
    creep, comp = ctx.drift.compensation(ctx.scan_ref, t_line)
    ctx.scan_creep.append(creep)
    if np.trace(comp) > np.trace(ctx.scan_comp):
        ctx.scan_comp = comp
    a, b = a + shift, b + shift
    lo, hi = ctx.config.lower[:2], ctx.config.upper[:2]
    s = np.linspace(0.0, 1.0, n)
    pts = a[None, :] + s[:, None] * (b - a)[None, :]
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    if inside.all():
        ends, count = (a, b), n
    else:
        idx = np.flatnonzero(inside)
        if idx.size < 2:
            return np.zeros(n)
        i0, i1 = int(idx[0]), int(idx[-1])
        ends, count = (pts[i0], pts[i1]), i1 - i0 + 1
    t0 = yield Msg("clock")
    profile = np.asarray((yield Msg("scan_line", (tuple(ends[0]), tuple(ends[1]), count))), float)
    t = yield Msg("clock")
    switched = ctx.timing.switched(count, t - t0)
    ctx.ledger.times["mode_switch"] += switched          # the switch back to tapping before it
    ctx.timing.observe(count, t - t0)
    ctx.timing.tapping = True
    if first:               # a switch to tapping delays the first line: the sample it saw is then
        ctx.scan_ref = t0 + switched
    ctx.drift.moved_to(ends[0], t0 + switched)
    ctx.drift.moved_to(ends[1], t)
    if count < n:
        out = np.full(n, float(np.median(profile)))
        out[i0:i1 + 1] = profile
        profile = out
    yield Msg("emit", ("scan_line", line_doc(ctx, a, b, profile, t)))
    return profile


def line_doc(ctx: RunContext, a, b, heights, t: float) -> dict:
    """A local-scan line: end points (scanner frame), heights, and the scanner position
    of the layout origin as estimated then (layout = scanner - offset)."""
    off = ctx.offset(ctx.drift.clamp(t))
    return {"t": t, "a": [float(a[0]), float(a[1])], "b": [float(b[0]), float(b[1])],
            "heights": np.asarray(heights, float).tolist(), "offset": [float(off[0]), float(off[1])]}


#: Directions tried for a particle's first line (degrees; its second is perpendicular).
DIRECTIONS = tuple(22.5 * k for k in range(8))


def clear_direction(ctx: RunContext, at, half: float, exclude=()) -> np.ndarray:
    """The direction of a particle's first scan line through ``at`` (layout frame) whose
    cross (that line and the perpendicular one, ``half`` nm to each side) stays farthest
    from the other believed objects: in a packed array a line along the rows runs into
    the neighbours and their bumps hide the one looked for. x when nothing is near."""
    import shapely

    objects = ctx.belief.objects
    others = [o for oid, o in ((oid, objects[oid]) for oid in objects.near(at, 2 * half))
              if oid not in exclude and oid not in ctx.belief.lost
              and math.dist(o.at, at) < 2 * half + (o.length or o.diameter)]
    if not others:
        return np.array([1.0, 0.0])
    cores = [o.geometry() for o in others]
    radii = np.array([o.radius for o in others])
    best, best_gap = np.array([1.0, 0.0]), -math.inf
    for deg in DIRECTIONS:
        u = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])
        v = np.array([-u[1], u[0]])
        lines = [shapely.LineString([at - half * w, at + half * w]) for w in (u, v)]
        gap = min(float(shapely.distance(ln, c)) - r for ln in lines for c, r in zip(cores, radii))
        if gap > best_gap + 1e-9:
            best, best_gap = u, gap
    return best


def _pose(o, centre, angle) -> Body:
    """The located pose of belief object ``o`` at ``centre`` (a rod's measured angle)."""
    angle = angle if o.kind == "rod" and angle is not None else o.angle
    return Body(o.id, o.kind, (float(centre[0]), float(centre[1])), o.diameter,
                angle if o.elongated else None, o.length if o.elongated else None)


def locate(ctx: RunContext, obj_id: str, *, widen: bool = True, resolve: bool = True, shift=None):
    """Local scan of an object where it is believed to be; widening search if missed
    (and ``widen``). What the scan found is associated with the belief
    (:func:`identify`; ``resolve``: an ambiguous sighting is resolved by scanning the
    other candidates). ``shift`` (layout frame, nm): looked for that far from where it is
    believed, as a hypothesis of where everything lies would put it.

    Returns (measured pose in the *scanner* frame, covariance, time, scan result) or
    None (lost, or not where expected). Convert with ``ctx.to_layout`` after any drift
    update.
    """
    o = ctx.belief[obj_id]
    t = yield Msg("clock")
    off = ctx.offset(t)
    r_max = ctx.r_max(t, obj_id)
    believed = ctx.position(obj_id) + (0.0 if shift is None else np.asarray(shift, float))
    at = believed + off
    if o.kind == "rod":
        pattern = rod_before(at, o.angle, o.length, o.diameter, r_max, measure_angle=True, options=ctx.scan_opts)
    else:
        half = o.radius + r_max + ctx.scan_opts.resolved(o.diameter).margin
        direction = clear_direction(ctx, believed, half, exclude={obj_id})
        pattern = particle_before(at, o.diameter, r_max, direction=direction, options=ctx.scan_opts)
    res = yield from run_pattern(ctx, pattern)
    t_seen, seen_at = _seen(ctx, res, t)
    gate = r_max + o.radius + ctx.scan_opts.resolved(o.diameter).margin     # as far as its lines reach
    expected = None if shift is None else tuple(believed)
    if res.found and not (yield from identify(ctx, obj_id, res, seen_at, gate, expected=expected,
                                                         resolve=resolve, adopt=shift is None)):
        res = replace(res, found=False)
    if not res.found and shift is None and o.kind != "rod" and any(ln.edges.reason in CROWDED for ln in res.lines):
        seen = yield from _locate_by_image(ctx, obj_id, r_max, gate, resolve)
        if seen is not None:
            return seen
    if not res.found and not widen:
        yield Msg("event", (f"{obj_id} not found within {r_max:.0f} nm",), {"level": "warn"})
        return None
    if not res.found:
        yield Msg("event", (f"{obj_id} not found within {r_max:.0f} nm; widening search",), {"level": "warn"})
        res = yield from run_pattern(ctx, find_lost_particle(at, o.diameter, ctx.options.lost_radius,
                                                             options=replace(ctx.scan_opts, max_lines=400)))
        if res.found and o.kind == "rod":
            res = yield from run_pattern(ctx, rod_before(res.centre, o.angle, o.length, o.diameter,
                                                         2 * o.diameter, measure_angle=True, options=ctx.scan_opts))
        t_seen, seen_at = _seen(ctx, res, t)
        if not res.found or not (yield from identify(ctx, obj_id, res, seen_at,
                                                     math.sqrt(2.0) * ctx.options.lost_radius, resolve=resolve)):
            return None
    cov = res.cov if res.cov is not None else np.eye(2) * DEFAULT_COV
    return _pose(o, np.asarray(res.centre, float), res.angle), np.asarray(cov, float), t_seen, res


def _seen(ctx: RunContext, res, t: float):
    """When the sample lay as the pattern just run saw it, its first line (``ctx.scan_ref``;
    ``t`` if it ran none), and where (layout frame) it found ``res``'s centre (None if it
    found none), with the offset of then, taken at once: resolving an ambiguous sighting
    scans other objects, which moves ``ctx.scan_ref`` on. Not the offset of when the
    search began: a widening search starts seconds after the scan that missed, while creep
    after the travel moved the sample (wide seed 7: 28 nm in 3 s, and the sighting of a
    neighbour, 1 nm from where it was believed, read 39 nm from it, was taken for the
    object looked for)."""
    t_seen = ctx.scan_ref if ctx.scan_ref is not None else t
    return t_seen, (np.asarray(res.centre, float) - ctx.offset(t_seen) if res.found else None)


def _locate_by_image(ctx: RunContext, obj_id: str, r_max: float, gate: float, resolve: bool):
    """A particle whose lines ran into a neighbour (a touching one, or one the belief
    does not know of where a line ends), looked for in a small image (plan stub): the
    round apex nearest where it is believed, within ``gate``, associated as a line's
    sighting is (:func:`identify`). Returns what :func:`locate` does, or None."""
    o = ctx.belief[obj_id]
    believed = ctx.position(obj_id)
    got = yield from image_check(ctx, believed, o.diameter, r_max, obj_id)
    if got is None:
        return None
    apices, pixels = got
    near = [(a, at, t) for a, at, t in apices if a.roundness >= ROUND and math.dist(at, believed) <= gate]
    if not near:
        yield Msg("event", (f"{obj_id}: its lines ran into a neighbour; an image of {pixels} x {pixels} px "
                            f"shows no particle within {gate:.0f} nm",), {"level": "warn"})
        return None
    a, at, t = near[0]
    cov = apex_cov(ctx, a)
    res = LocalScanResult("particle_image", True, "found", centre=tuple(np.asarray(at) + ctx.offset(t)), cov=cov)
    ctx.scan_ref, ctx.scan_creep = t, []            # the image's content is of its first line's time
    yield Msg("event", (f"{obj_id}: its lines ran into a neighbour; an image of {pixels} x {pixels} px shows a "
                        f"particle {math.dist(at, believed):.1f} nm from where it was believed, {a.height:.0f} nm high",))
    if not (yield from identify(ctx, obj_id, res, at, gate, resolve=resolve, height=a.height)):
        return None
    return _pose(o, np.asarray(res.centre, float), None), cov, t, res


#: Objects farther than this (nm) from a sighting are not compared with it.
ASSOCIATION_REACH = 1000.0


def identify(ctx: RunContext, obj_id: str, res, at, gate: float, *, expected=None, resolve: bool = True,
             height: float | None = None, adopt: bool = True):
    """Whether the object a located scan result ``res`` shows at ``at`` (layout frame) is
    ``obj_id`` (believed at ``expected``, by default where the belief puts it, within
    ``gate`` nm): :func:`~.association.associate` against every believed object near.

    A sighting that another object explains as well is resolved by scanning where those
    are believed (``resolve``): one found elsewhere is not what was seen (and its
    sighting is kept); one found at ``at`` is. Unresolved, the sighting goes to the
    candidate it lies nearer to, relative to their gates. A sighting no believed object
    explains is added to the belief as a new object. Events say which happened.
    ``height``: the sighting's height (nm) where ``res`` has no lines to tell it (an
    image's apex). ``adopt``: False where the sighting of a hypothesis only (``expected``
    not the belief's) is no evidence of a new object."""
    t = ctx.scan_ref if ctx.scan_ref is not None else (yield Msg("clock"))
    at = np.asarray(at, float)
    cov = res.cov if res.cov is not None else np.eye(2) * DEFAULT_COV
    seen_height, noise = sighting(res)
    height = seen_height if height is None else height
    o = ctx.belief[obj_id]
    me = Candidate(obj_id, tuple(ctx.position(obj_id) if expected is None else expected), gate, o.diameter)
    objects = ctx.belief.objects
    others = [Candidate(oid, tuple(ctx.position(oid)), ctx.r_max(t, oid), b.diameter)
              for oid, b in ((oid, objects[oid]) for oid in objects.near(at, ASSOCIATION_REACH))
              if oid != obj_id and oid not in ctx.belief.lost and math.dist(b.at, at) < ASSOCIATION_REACH]
    assoc = associate(me, others, at, cov, height, noise)
    if assoc.kind == "match":
        return True
    yield Msg("event", (assoc.text(obj_id),), {"level": "warn"})
    if assoc.kind == "new" and adopt:
        new = ctx.add_new(o.kind, at, height if height is not None else o.diameter, o, t,
                          ctx.drift.observation_cov(t, cov))
        rod = o.kind != "particle"          # an obstacle, never assigned (:meth:`RunContext.add_new`)
        yield Msg("event", (f"{new}: a new object at ({at[0]:.0f}, {at[1]:.0f}) nm, "
                            f"{height if height is not None else o.diameter:.0f} nm high"
                            + (": an obstacle" if rod else ""),), {"level": "warn"})
        return False
    if assoc.kind in ("other", "new") or not resolve:
        return assoc.kind == "ambiguous" and _nearer(me, others, assoc.others, at)
    for oid in assoc.others[:2]:
        found = yield from locate(ctx, oid, widen=False, resolve=False)
        if found is None:
            if not _nearer(me, others, (oid,), at):
                yield Msg("event", (f"{obj_id}: not told apart from {oid}; taken as {oid}",), {"level": "warn"})
                return False
            continue
        scanner, c_cov, t_c = found[:3]
        seen_at = ctx.to_layout(scanner, t_c)
        if math.dist(seen_at.at, at) <= 0.5 * min(o.diameter, ctx.belief[oid].diameter):
            yield Msg("event", (f"{obj_id}: what was found is {oid}",), {"level": "warn"})
            return False
        ctx.observe(oid, seen_at.at, t_c, c_cov, angle=seen_at.angle)
    yield Msg("event", (f"{obj_id}: told apart from {', '.join(assoc.others[:2])}",), {"level": "info"})
    return True


def _nearer(me: Candidate, others: list[Candidate], ids, at) -> bool:
    """Whether ``at`` lies nearer to ``me`` than to the candidates ``ids``, each distance
    relative to its gate."""
    gates = {c.id: c for c in others}
    q = math.dist(at, me.at) / me.gate
    return all(q < math.dist(at, gates[i].at) / gates[i].gate for i in ids)


def scan_after(ctx: RunContext, op: Operation, start: Body):
    """Local scan after a push: where did the object go? (layout pose, cov, t) or None."""
    o = ctx.belief[op.object]
    t = yield Msg("clock")
    off = ctx.offset(t)
    r_max = ctx.r_max(t, op.object) + 0.1 * math.dist(start.at, op.expect.at)
    a = np.asarray(op.tip_path[0])
    b = np.asarray(op.tip_path[-1])
    delta = float(np.linalg.norm(b - a))
    u = (b - a) / delta if delta > 0 else np.array([1.0, 0.0])
    if o.kind == "rod":
        scan = rod_after if ctx.options.after_scan == "seed" else rod_after_predicted
        pattern = scan(np.asarray(start.at) + off, start.angle, o.length, o.diameter,
                            b - u * delta / 2 + off, u, delta, r_max,
                            predicted=np.asarray(op.expect.at) + off,
                            predicted_angle=op.expect.angle, options=ctx.scan_opts)
    else:
        move = np.asarray(op.expect.at) - np.asarray(start.at)
        length = float(np.linalg.norm(move))
        direction = move / length if length > 0 else u
        scan = particle_after_predicted if ctx.options.after_scan == "predicted" else particle_after
        pattern = scan(np.asarray(start.at) + off, o.diameter, direction, length, r_max, options=ctx.scan_opts)
    res = yield from run_pattern(ctx, pattern)
    if not res.found:
        return None
    t = ctx.scan_ref if ctx.scan_ref is not None else (yield Msg("clock"))
    centre = np.asarray(res.centre, float) - ctx.offset(t)
    a0, a1 = np.asarray(start.at, float), np.asarray(op.expect.at, float)
    span = float(np.dot(a1 - a0, a1 - a0))
    on_path = a0 + (a1 - a0) * (np.clip(np.dot(centre - a0, a1 - a0) / span, 0.0, 1.0) if span > 0 else 0.0)
    # the pushed object may have stopped anywhere along its push: its gate is about the path
    reach = r_max + o.radius + ctx.scan_opts.resolved(o.diameter).margin
    if not (yield from identify(ctx, op.object, res, centre, reach, expected=on_path)):
        return None                  # the lines found a neighbour, not the pushed object
    return _pose(o, centre, res.angle), np.asarray(res.cov if res.cov is not None else np.eye(2) * DEFAULT_COV), t
