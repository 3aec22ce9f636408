"""A rod's outline from the lines of a pattern (seed 5.3, Fig. 5.2): the axis line V
through the cross lines' midpoints, and the least-squares fit of the outline (a capsule
around the rod's core, :func:`~nanoasm.executor.capsule_fit.fit_capsule`) to every
crossing.

Where V cannot see both of the rod's ends, the rod is placed at its believed length:
one end seen clear (the other ran off the line or into a touching neighbour), or both
ends hidden by neighbours whose tip-broadened images meet the rod's above its half
height (a rod between two particles a few tens of nm from its ends): then V's crossings
at a level above both saddles, symmetric about the rod's centre, place it along its axis.
"""

from __future__ import annotations

import math

import numpy as np

from .capsule_fit import fit_capsule, near_angle
from .substrate import substrate_through
from .scan_lines import LocalScanResult, ScanLine, axis, make_line, measure_line, missed, perp, wedge

#: A fit less certain of the angle than this (degrees, 1-sigma) is refused.
MAX_ANGLE_STD = 10.0
#: A rod seen at one end only is placed by cross lines whose summits are all within
#: this share of its believed diameter (identification measures it to about 1 %).
ONE_END_HEIGHT = 0.1


def _substrate(line, cross):
    """The substrate the cross lines measured, along ``line`` (whose ends may lie on particles)."""
    return substrate_through([(float((o.midpoint() - line.a) @ line.direction), o.edges.substrate,
                               o.edges.noise) for o in cross], line.length)


def _axis_line(mids, w, ref, L, r_max, opts, role):
    """Line along ``w`` through ``mids[0]`` spanning every place of a rod of length ``L``
    that contains all ``mids`` and whose centre is (if that is consistent) within
    ``r_max`` of ``ref``. Returns the line and where ``mids[0]`` lies on it (nm from a)."""
    ts = [float((m - ref) @ w) for m in mids]
    lo, hi = max(ts) - L / 2, min(ts) + L / 2
    if max(lo, -r_max) <= min(hi, r_max):
        lo, hi = max(lo, -r_max), min(hi, r_max)
    origin = mids[0] - ts[0] * w
    s_lo = lo - L / 2 - opts.margin
    line = make_line(origin, w, s_lo, hi + L / 2 + opts.margin, opts.spacing, role)
    return line, ts[0] - s_lo


def _fit_lines(outcomes, c0, w, half0, rad0, fix_angle, end=None):
    """The outline through the crossings of ``outcomes``; with ``end`` (a line's one clear
    crossing: point, line direction, 1-σ), through it too at the half-length ``half0``."""
    pts = np.concatenate([o.crossings() for o in outcomes])
    dirs = np.repeat([o.line.direction for o in outcomes], 2, axis=0)
    stds = np.array([s for o in outcomes for s in (o.edges.left_std, o.edges.right_std)])
    if end is not None:
        pts, dirs, stds = np.vstack([pts, end[0]]), np.vstack([dirs, end[1]]), np.append(stds, end[2])
    ang = math.degrees(math.atan2(w[1], w[0]))
    return fit_capsule(pts, dirs, stds, c0, ang, half0, rad0, fix_angle=fix_angle, fix_half=end is not None)


def _misses_ends(line: ScanLine, fit) -> bool:
    """Whether ``line`` passes an end of the fitted core farther than half its radius."""
    a_hat = axis(fit.angle)
    nrm = perp(line.direction)
    ends = [fit.centre - fit.half * a_hat, fit.centre + fit.half * a_hat]
    return max(abs(float((e - np.asarray(line.a)) @ nrm)) for e in ends) > 0.5 * fit.radius


def _hidden_ends(pattern, cross, touches, vline, vout, w, th_ref, L, d, rad0, fix_angle, lines, opts):
    """The outline at the believed length (``length_std`` None: not measured) from the
    cross lines and what line V saw of the ends: one end clear (the other ran into a
    touching neighbour or off the line), or the rod's crossings above the saddles to
    neighbours at both ends, whose midpoint is the rod's centre along V."""
    # without the other end's check of the length, every cross line must be the rod's
    # height: one that crossed a particle beside the rod would tilt the axis
    seen = "one end only" if vout.edges.inner is None else "neither end clear of its neighbours"
    share = max(ONE_END_HEIGHT, opts.rod_height or 0.0)
    if any(abs(o.edges.peak - d) > share * d + 3 * o.edges.noise for o in (*cross, *touches)
           if o.edges.peak is not None):
        return missed(pattern, f"line V along the rod saw {seen} ({vout.edges.reason}), and a cross "
                      f"line is not of the rod's height", lines)
    half = (L - d) / 2
    u = vline.direction
    if vout.edges.inner is None:
        at, std, side = vout.edges.end
        end_pt = vline.at(at)
        c0 = end_pt - side * (half + rad0) * u
        end = (end_pt, u, std)
    else:                                   # two outline points as far from the centre
        left, right, left_std, right_std, _ = vout.edges.inner
        c0 = vline.at(0.5 * (left + right))
        end = (np.array([c0 - (half + rad0) * u, c0 + (half + rad0) * u]), np.array([u, u]),
               np.full(2, math.hypot(left_std, right_std) / math.sqrt(2.0)))
    fit = _fit_lines([*cross, *touches], c0, w, half, rad0, fix_angle, end=end)
    if fit is None:
        return missed(pattern, f"line V along the rod saw {seen} ({vout.edges.reason}), and the "
                      f"crossings do not place the rod by it", lines)
    return _result(pattern, fit, th_ref, d, fix_angle, lines, L, None,
                   "one end seen; " if vout.edges.inner is None else "ends hidden; ")


def _result(pattern, fit, th_ref, d, fix_angle, lines, length, length_std, note=""):
    """The scan's result from an outline fit, refused where it hardly fixes the rod."""
    cov = fit.cov
    angle_std = None if fix_angle else float(math.sqrt(max(cov[2, 2], 0.0)))
    centre_std = math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2])[-1], 0.0))
    if centre_std > d / 2 or (angle_std is not None and angle_std > MAX_ANGLE_STD):
        return missed(pattern, f"{note}the crossings hardly determine the rod's outline (centre "
                      f"1-sigma {centre_std:.3g} nm)", lines)
    return LocalScanResult(pattern, True, "found", (float(fit.centre[0]), float(fit.centre[1])),
                           cov[:2, :2].copy(), near_angle(fit.angle, th_ref), angle_std, length,
                           length_std, tuple(lines))


def finish_rod(pattern, cross, w, ref, th_ref, L, d, r_max, opts, fix_angle, lines, prime,
                touches=()):
    """Scan the axis line V through the cross lines' midpoints and fit the outline to
    their crossings, V's and those of lines that only grazed an end (``touches``)."""
    vline, s_exp = _axis_line([o.midpoint() for o in cross], w, ref, L, r_max, opts, "V" + prime)
    vout = yield from measure_line(vline, s_exp, opts, _substrate(vline, cross))
    lines.append(vout)
    rad0 = float(np.mean([o.edges.width * abs(wedge(o.line.direction, w))
                          for o in cross])) / 2
    if not vout.edges.found:
        if vout.edges.end is None and vout.edges.inner is None:
            return missed(pattern, f"line V{prime} along the rod found no ends ({vout.edges.reason})",
                          lines)
        return _hidden_ends(pattern, cross, touches, vline, vout, w, th_ref, L, d, rad0, fix_angle, lines,
                            opts)
    c0 = vline.at(vout.edges.centre)
    used = [*cross, *touches, vout]
    fit = _fit_lines(used, c0, w, vout.edges.width / 2 - rad0, rad0, fix_angle)
    if fit is not None and not fix_angle and _misses_ends(vline, fit) \
            and len(lines) < opts.max_lines:
        w2 = axis(fit.angle)
        line2, s2 = _axis_line([fit.centre], w2, ref, L, r_max, opts, "V" + prime + "2")
        out2 = yield from measure_line(line2, s2, opts, _substrate(line2, cross))
        lines.append(out2)
        if out2.edges.found:
            used.append(out2)
            fit = _fit_lines(used, fit.centre, w2, fit.half, fit.radius, False)
    if fit is None:
        return missed(pattern, "the crossings do not determine the rod's outline", lines)
    length = 2 * fit.half + d
    if abs(length - L) > max(opts.length_tolerance * L, d):
        return missed(pattern, f"the fitted outline is {length:.4g} nm long, not about the "
                      f"believed {L:.4g} nm", lines)
    return _result(pattern, fit, th_ref, d, fix_angle, lines, length, 2 * float(math.sqrt(max(fit.cov[3, 3], 0.0))))
