"""A repair round after the check scans: survey the particle slots left unfilled, take
the belief from what the survey sees, and plan again.

A push that went astray when the drift jumped, or that shoved a neighbour, leaves the
belief wrong in a way no local scan of one object repairs: the object is lost, or was
taken for its neighbour, and the slot stays empty though the object lies a hundred
nanometres off. The check scans tell which slots are not filled. A small raster scan
(:data:`SURVEY_MARGIN` beyond each such slot, the object assigned to it and any two
believed particles that overlap, at the full scan's pixel size, windows merged up to
:data:`MAX_SURVEY` a side, a drift reference before each) is identified as the full scan
was (:func:`~nanoasm.world.identify.identify`), each object put into the layout frame with
the drift estimate at the time its row was scanned, and matched to the belief by least
total distance (:func:`scipy.optimize.linear_sum_assignment`):

- a believed object (lost ones included) matched to a sighting is observed there and
  found again; one that moved beyond its uncertainty is no drift reference any more;
- a believed particle (not lost) well inside the window (:data:`SEEN_MARGIN`) that no
  sighting matches stays as it was if it lies in a clump the identification could not
  resolve (particles packed closer than the tip resolves); otherwise a local scan looks
  for it where it is believed, and it is lost only if that does not find it either. A
  rod is never lost by a survey (a small window's identification may take a rod beside
  particles for a clump, or a slender one for a wire);
- a particle seen where no believed object can be is added (``new<k>``); any other
  unmatched sighting (a rod) is added as an obstacle the planner works around.

Particles still lost are then looked for where their pushes went (:func:`lost_windows`):
a sighting there that nothing believed explains is that particle, however far it went.
The caller plans what remains from that belief and pushes again; a run makes at most
:attr:`~nanoasm.executor.strategy.ExecOptions.repair_rounds` such rounds. Rod slots are
left to the rod's own course (:func:`_particle_slots_not_filled`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from nanoasm.world.identify import identify

from .context import RunContext
from .drift_steps import take_reference
from .edge_slots import edge_line, edge_pushes, edge_slots
from .engine import Msg
from .progress_docs import PROGRESS, ProgressDoc
from .relocalise import keep_track
from .scan_images import scan_window
from .scan_steps import locate
from .summary import summary
from .verdict import check_again

#: Substrate surveyed beyond a slot's footprint, nm: a push gone astray leaves its object
#: and the neighbours it shoved within a few hundred nm.
SURVEY_MARGIN = 250.0
#: Largest side of one survey window, nm (nearby slots share a window up to this).
MAX_SURVEY = 1500.0
#: How far (nm) survey tiles reach into their neighbours: past a particle's diameter.
TILE_OVERLAP = 100.0
#: A believed object not seen is lost only this far (nm) inside the window's edges.
SEEN_MARGIN = 100.0
#: A believed object whose centre is inside a clump the survey could not resolve
#: (touching objects read as one), or this close to it (nm), may be in it: not lost.
CLUMP_REACH = 20.0
#: Farthest a believed object (not lost) may be matched from where it was believed, nm.
GATE = 400.0
#: Farthest a lost object may be matched from where it was last believed, nm.
GATE_LOST = 800.0


def _box(body, margin: float) -> tuple[float, float, float, float]:
    """A body's (a slot's, an object's) footprint plus ``margin`` as a window."""
    (x, y), half = body.at, (body.length / 2.0 if body.elongated else 0.0) + body.radius + margin
    return (x - half, y - half, x + half, y + half)


def merge_windows(boxes, largest: float = MAX_SURVEY) -> list[tuple[float, float, float, float]]:
    """``boxes`` (``(x0, y0, x1, y1)``) merged greedily while a merged window stays within
    ``largest`` a side (a box larger than that on its own stays one window)."""
    boxes = list(boxes)
    merged = True
    while merged:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                u = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                if max(u[2] - u[0], u[3] - u[1]) <= largest:
                    boxes[i] = u
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


def tiles(area, margin: float = SURVEY_MARGIN, largest: float = MAX_SURVEY,
          overlap: float = TILE_OVERLAP) -> list[tuple[float, float, float, float]]:
    """Square windows covering a shapely geometry widened by ``margin``: its bounding box
    cut into equal squares of at most ``largest`` a side, those that do not meet it left
    out, each widened by ``overlap`` (an object on a cut is whole in one of them)."""
    import shapely

    wide = area.buffer(margin)
    if wide.is_empty:
        return []
    x0, y0, x1, y1 = wide.bounds
    n = max(1, math.ceil(max(x1 - x0, y1 - y0) / largest))
    side = max(x1 - x0, y1 - y0) / n
    out = []
    for i in range(max(1, math.ceil((x1 - x0) / side - 1e-9))):
        for j in range(max(1, math.ceil((y1 - y0) / side - 1e-9))):
            box = (x0 + i * side, y0 + j * side, x0 + (i + 1) * side, y0 + (j + 1) * side)
            if wide.intersects(shapely.box(*box)):
                out.append((box[0] - overlap, box[1] - overlap, box[2] + overlap, box[3] + overlap))
    return out


def _overlapping(ctx: RunContext) -> list[str]:
    """Believed particles (not lost) that overlap another by more than half the smaller's
    diameter (:meth:`~.belief.Belief.taken`): two objects cannot be there; one of them is a
    mistaken identity."""
    b = ctx.belief
    return sorted(oid for oid, o in b.objects.items()
                  if o.kind == "particle" and oid not in b.lost and b.taken(oid, o.at))


def doubtful_windows(ctx: RunContext, bad) -> list[tuple[float, float, float, float]]:
    """Where a repair round looks first: every particle slot not filled (``bad``, as
    :func:`_particle_slots_not_filled` gives them), the object assigned to it, and believed
    particles that overlap another (:data:`SURVEY_MARGIN` around each)."""
    boxes = []
    for target, v in bad:
        boxes.append(_box(target, SURVEY_MARGIN))
        if v.object in ctx.belief.objects and v.object not in ctx.belief.lost:
            boxes.append(_box(ctx.belief[v.object], SURVEY_MARGIN))
    boxes += [_box(ctx.belief[oid], SURVEY_MARGIN) for oid in _overlapping(ctx)]
    return merge_windows(boxes)


def lost_windows(ctx: RunContext, surveyed=()) -> list[tuple[tuple[float, float, float, float], set[str]]]:
    """Where a repair round looks for particles still lost, and which it looks for there:
    the areas their pushes swept, the latest first (a push gone astray leaves its object
    near where it went; one that went unnoticed, near an earlier one's), less what the
    windows ``surveyed`` already show (a tile mostly inside them is left out)."""
    import shapely

    seen = shapely.union_all([shapely.box(*_shrunk(w)) for w in surveyed]) if surveyed else shapely.Polygon()
    out: dict[tuple[float, float, float, float], set[str]] = {}
    for oid in sorted(ctx.belief.lost):
        if oid in ctx.ledger.given_up or ctx.belief[oid].kind != "particle":
            continue
        for area in reversed([a for a in ctx.refs.pushes if a.obj == oid]):
            for box in tiles(area.geometry()):
                tile = shapely.box(*_shrunk(box))
                if tile.difference(seen).area > 0.25 * tile.area:
                    out.setdefault(box, set()).add(oid)
                    seen = seen.union(tile)
    return list(out.items())


def _shrunk(window) -> tuple[float, float, float, float]:
    """A window less its rim, where objects are cut by the edge."""
    m = SEEN_MARGIN
    return (window[0] + m, window[1] + m, window[2] - m, window[3] - m)


#: Survey windows one repair round scans at most (a window of 1.5 µm at 10 nm a pixel
#: takes 150 lines).
MAX_WINDOWS = 8


def repair_round(asm, done: int):
    """A repair round of the assembly ``asm`` (after its check scans, ``done`` operations
    of its plan run) if slots are not filled, or filled only near the edge of their
    tolerance (:mod:`.edge_slots`), rounds remain and the run pushed something (else the
    belief is what the full scan showed, which a survey at its pixel size would only
    repeat): survey the slots not filled and plan again from what the survey saw, then
    push the particles at the edge in; returns the operations (none: the run is over; a
    replan with no push checks the slots not filled again,
    :func:`~.verdict.check_again`)."""
    ctx = asm.ctx
    bad = _particle_slots_not_filled(asm.layout, asm.slots)
    edge = edge_slots(asm.layout, asm.slots, ctx)
    if not (bad or edge) or not asm.strategy.replans or ctx.ledger.repairs >= asm.options.repair_rounds \
            or not ctx.ledger.pushed:               # nothing pushed: the belief is the full scan's
        return []
    ctx.ledger.repairs += 1
    if ctx.ledger.repairs == 1:
        yield Msg("emit", (PROGRESS, ProgressDoc("phase", "repair")))
    ops = []
    if bad:
        yield Msg("event", (f"repair round {ctx.ledger.repairs}: surveying the {len(bad)} particle slot(s) "
                            f"not filled",), {"level": "warn"})
        yield from survey(ctx, bad, asm.slots, asm.plan_options.tip_radius)
        ops = yield from asm.replan(done, f"repair round {ctx.ledger.repairs}")
    held = {(a.target, a.object) for a in summary(asm).assignment}
    edge = [(t, v) for t, v in edge if (t.id, v.object) in held and all(p.object != v.object for p in ops)]
    extra = edge_pushes(asm.layout, ctx, edge, asm.plan_options,
                        max([*asm.course.starts, *(p.id for p in ops)], default=0) + 1)
    if extra:
        yield Msg("event", (f"repair round {ctx.ledger.repairs}: " + edge_line(edge, len(extra)),))
        asm.course.follow(ctx.environment(), extra, extend=True)
        ctx.moving = {p.object for p in ops} | {p.object for p in extra}
        asm.recheck = None if bad else {t.id for t, _ in edge}
        ops += extra
    if bad and not ops:          # nothing to push: perhaps the last check scans looked amiss
        asm.slots = yield from check_again(ctx, asm.layout, summary(asm).assignment, asm.slots)
    return ops


def _particle_slots_not_filled(layout, verdicts) -> list:
    """(target, verdict) of the particle slots the check scans did not find filled with
    nothing found within the position tolerance: an object found there, of the wrong size
    or shape, is no matter of where things are (a rod slot's repair is its
    receding-horizon course: a survey cannot tell a rod from the particles beside it in a
    device layout, and replanning a rod costs tens of pushes)."""
    tol = layout.tolerance.position
    return [(t, v) for t, v in zip(layout.targets, verdicts)
            if v.state != "filled" and t.kind == "particle" and (v.error is None or v.error > tol)]


def spare_particles(ctx: RunContext, verdicts=()) -> int:
    """Particles the planner may still bring to a slot: believed, not lost, not given
    up, not what a filled slot holds (``verdicts``: the check scans', if any)."""
    holding = {v.object for v in verdicts if v.state == "filled"}
    return sum(o.kind == "particle" and oid not in ctx.belief.lost and oid not in ctx.ledger.given_up
               and oid not in holding for oid, o in ctx.belief.objects.items())


def survey(ctx: RunContext, bad, verdicts, tip_radius: float):
    """Scan windows around the particle slots not filled (plan stub; ``bad``: those slots
    and their verdicts, :func:`_particle_slots_not_filled`; ``verdicts``: every slot's) and
    set the belief from what they show; then, if the particles left are fewer than those
    slots, windows where particles still lost were pushed."""
    first = doubtful_windows(ctx, bad)[:MAX_WINDOWS]
    for k, window in enumerate(first):
        yield from survey_window(ctx, window, k + 1, tip_radius)
    if spare_particles(ctx, verdicts) >= len(bad):
        return                                           # enough to fill them without the lost
    todo = lost_windows(ctx, [*first, *ctx.surveyed])[:MAX_WINDOWS - len(first)]
    for k, (window, sought) in enumerate(todo):
        if not sought & ctx.belief.lost:
            continue                                     # found again meanwhile
        yield from survey_window(ctx, window, len(first) + k + 1, tip_radius, sought)
        ctx.surveyed.append(window)                      # not looked at again for the lost


def survey_window(ctx: RunContext, window, k: int, tip_radius: float, sought: set[str] = frozenset(),
                  pixel: float | None = None):
    """One survey window (layout frame): scanned where the estimate puts it, a drift
    reference measured before it, identified, associated with the belief (a
    sighting nothing believed matches is taken for the nearest of the lost objects
    ``sought`` there). ``pixel``: its pixel size, nm (the full scan's by default)."""
    if pixel is None:
        pixel = ctx.full_scan.pixel_size if ctx.full_scan is not None else ctx.options.pixel_size
    lo, hi = np.asarray(ctx.config.lower[:2], float), np.asarray(ctx.config.upper[:2], float)
    middle = 0.5 * (np.asarray(window[:2]) + np.asarray(window[2:]))
    yield from keep_track(ctx)
    yield from take_reference(ctx, middle)
    t0 = yield Msg("clock")
    off = ctx.offset(t0)
    half = 0.5 * max(window[2] - window[0], window[3] - window[1])     # square: one pixel size
    x0, y0 = np.maximum(middle + off - half, lo)
    x1, y1 = np.minimum(middle + off + half, hi)
    side = min(x1 - x0, y1 - y0)
    if side < 10.0 * pixel:
        return
    x1, y1 = x0 + side, y0 + side
    pixels = max(16, int(round(side / pixel)))
    scan, t1 = yield from scan_window(ctx, pixels, (x0, y0, x1, y1), f"survey window {k}")
    env = identify(scan, tip_radius=tip_radius)
    corner, line_time = np.asarray(env.origin, float), (t1 - t0) / pixels

    def seen(at) -> tuple[np.ndarray, float]:       # a scan point in the layout frame, by its row's time
        at = np.asarray(at, float) + corner
        t = t0 + (min(max((at[1] - y0) / (side / pixels), 0.0), pixels - 1.0) + 0.5) * line_time
        return at - ctx.offset(t), t

    found = []
    for o in env.objects:
        if not o.edge and o.kind in ("particle", "rod"):
            at, t = seen(o.at)
            found.append((replace(o, at=(float(at[0]), float(at[1]))), t))
    clumps = [(np.array([seen(p)[0] for p in ob.polygon]), ob.height) for ob in env.obstacles]
    region = (float(x0 - off[0]), float(y0 - off[1]), float(x1 - off[0]), float(y1 - off[1]))
    lines, unseen = _associate(ctx, region, found, clumps, pixel, sought)
    for oid in unseen:            # a crowded window may hide what a local scan still finds
        located = yield from locate(ctx, oid, widen=False)
        if located is None:
            ctx.belief.lose(oid)
            lines.append(f"{oid} is not there")
        else:
            scanner, cov, t = located[:3]
            ctx.observe(oid, ctx.to_layout(scanner, t).at, t, cov)
    yield Msg("event", (f"survey {k} of ({region[0]:.0f}, {region[1]:.0f})-({region[2]:.0f}, "
                        f"{region[3]:.0f}), {pixels} x {pixels} px: {len(found)} object(s) seen"
                        + ("; " + "; ".join(lines) if lines else "; the belief holds"),))


def _inside(o, region, margin: float = 0.0) -> bool:
    r = o.radius + (o.length / 2.0 if o.elongated else 0.0) + margin
    return region[0] + r <= o.at[0] <= region[2] - r and region[1] + r <= o.at[1] <= region[3] - r


def _associate(ctx: RunContext, region, found, clumps, pixel: float, sought=frozenset()):
    """Match the survey's sightings (``found``: (object in the layout frame, time)) to
    the belief (see the module docstring); returns a line per change and the believed
    particles the survey should have seen and did not (the caller scans for them). ``clumps``:
    outlines (layout frame) of what the survey could not resolve into objects (particles
    touching), with their heights: a believed object near one at least half its height
    is neither observed nor lost."""
    import shapely
    from scipy.optimize import linear_sum_assignment

    belief, out = ctx.belief, []
    near = [oid for oid, o in belief.objects.items()
            if oid not in ctx.ledger.given_up and o.kind in ("particle", "rod")
            and ((oid in belief.lost and _inside(o, region, -GATE_LOST))
                 or (oid not in belief.lost and _inside(o, region)))]
    where = {oid: ctx.position(oid) for oid in near}
    blobs = [(shapely.Polygon(c), h) for c, h in clumps if len(c) >= 3]
    hidden = {oid for oid in near if any(h >= 0.5 * belief[oid].diameter
                                         and b.distance(shapely.Point(*where[oid])) <= CLUMP_REACH
                                         for b, h in blobs)}
    cost = np.full((len(near), len(found)), 1e9)
    for i, oid in enumerate(near):
        o = belief[oid]
        gate = GATE_LOST if oid in belief.lost else GATE
        for j, (s, _) in enumerate(found):
            d = math.dist(where[oid], s.at)
            if s.kind == o.kind and d <= gate:
                # relative to its gate: a lost object's last belief says less of where it
                # is than a believed one's (allpushed seed 9, a jump at 750 s: by plain
                # distance a particle just pushed into its slot and a lost one were swapped)
                cost[i, j] = d / gate
    rows, cols = linear_sum_assignment(cost) if cost.size else ((), ())
    matched_b, matched_f = set(), set()
    cov = np.eye(2) * (0.5 * pixel) ** 2
    for i, j in zip(rows, cols):
        if cost[i, j] >= 1e9:
            continue
        oid, (s, t) = near[i], found[j]
        matched_b.add(oid)
        matched_f.add(j)
        d = math.dist(where[oid], s.at)
        was_lost = oid in belief.lost
        spread = 3.0 * math.sqrt(float(np.linalg.eigvalsh(belief.seen[oid].cov)[-1])) + pixel
        if was_lost or d > spread:
            out.append(f"{oid} {'found again' if was_lost else 'seen'} {d:.0f} nm from where it was believed")
            if d > spread:
                ctx.refs.gated.add(oid)                 # moved: no drift reference any more
        belief.lost.discard(oid)
        ctx.observe(oid, s.at, t, cov, angle=s.angle if s.elongated else None)
    unseen = [oid for oid in near if oid not in matched_b | belief.lost | hidden
              and belief[oid].kind == "particle" and _inside(belief[oid], region, SEEN_MARGIN)]
    for j, (s, t) in enumerate(found):
        if j in matched_f or not _inside(s, region):
            continue
        lost = sorted((math.dist(ctx.position(oid), s.at), oid) for oid in sought
                      if oid in belief.lost and belief[oid].kind == s.kind)
        if lost:
            oid = lost[0][1]
            belief.lost.discard(oid)
            ctx.refs.gated.add(oid)
            ctx.observe(oid, s.at, t, cov, angle=s.angle if s.elongated else None)
            out.append(f"{oid} found again {lost[0][0]:.0f} nm from where it was last believed")
            continue
        new = ctx.add_new(s.kind, s.at, s.diameter, s, t, cov)      # not a particle: an obstacle
        out.append(f"{new} ({s.kind}) seen where nothing was believed"
                   + ("" if s.kind == "particle" else ": an obstacle"))
    return out, unseen
