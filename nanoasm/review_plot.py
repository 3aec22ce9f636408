"""The picture of ``nanoasm review LOG --plot FILE``: what a logged run did, drawn.

:func:`review_figure` draws a :class:`~nanoasm.review.Review` in five parts:

* before: the first full scan (grey: the darker, the higher; from the log's
  ``full_scan.npz`` attachment) with the layout's slots and keep-outs, the objects
  identified in it and, in a dry-run, the true objects (dotted);
* after: the executor's last belief, the truth and every push's tip path (green, red when
  it failed) over the same scan, faint (it shows the sample as it was before);
* drift: the estimate over time with its ±σ band and, in a dry-run, the true drift at each
  estimate's time (the harness's ``/sim/truth``), dashed;
* around the slots: the after panel again, on the slots' bounding box;
* slot errors: a panel for each of the :data:`ZOOMED` slots with the largest centre
  errors, centred on the slot with the outlines at true scale, and the error vector (slot
  centre to the object's centre) and the position tolerance's circle magnified by the
  factor the panel states: a 5 nm error is a visible arrow. In a dry-run the run's own
  belief of the object is dashed, with its vector in grey.

One id space: slots carry their ids, objects the run's ids (those of its events, its
table and its pushes); a true body is labelled ``truth: scene id <id>``, the only place
a scene's id appears. In SVG, text stays text and the parts carry ids (``before-slot-l1``,
``after-object-o5``, ``after-object-label-o5``, ``after-truth-p3``, ``zoom-l2``,
``error-l2``, ``true-drift-x``), so a picture can be checked.
"""
from __future__ import annotations

import math
import os

import numpy as np

from nanoasm.executor.documents import FAILED_VERDICTS
from nanoasm.planner.assign import axis_error
from nanoasm.previews import levelled, outline

#: How many slots the zoomed panels show at most (those with the largest errors).
ZOOMED = 6
#: The most pixels a side of the scan is drawn with (a larger scan is drawn thinned).
SHOWN_PIXELS = 800
SLOT, OBJECT, TRUTH, ERROR = "tab:blue", "black", "tab:purple", "tab:red"
OBJECT_FILL = (1.0, 0.8, 0.2, 0.6)


def review_figure(rev):
    """The review's figure (a :class:`matplotlib.figure.Figure`; no pyplot)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(20.0, 12.0), layout="constrained")
    top, bottom = fig.subfigures(2, 1, height_ratios=(3.0, 2.0))
    before, after, drift = top.subplots(1, 3)
    dotted = " (truth dotted)" if rev.truth_final else ""
    _scene(before, rev, rev.initial, rev.truth_initial, "before: identified over the full scan" +
           (" (truth dotted)" if rev.truth_initial else ""), panel="before", scan_alpha=0.6)
    _scene(after, rev, rev.final, rev.truth_final, f"after: belief{dotted}, push paths", panel="after",
           scan_alpha=0.25)
    _drift(drift, rev)
    region, *zooms = bottom.subplots(1, 1 + ZOOMED, width_ratios=(2.0, *[1.0] * ZOOMED))
    _slots_region(region, rev, f"after, around the slots{dotted}")
    _zooms(bottom, zooms, rev)
    status = "" if rev.complete else " (damaged log)" if rev.damage and rev.cut is None else " (incomplete log)"
    fig.suptitle(f"{os.path.basename(rev.path)}: {rev.filled} slot(s) filled, {rev.pushes} push(es){status}; "
                 f"objects by the run's ids")
    return fig


# -- the scene ---------------------------------------------------------------------------

def _scene(ax, rev, bodies, truth, title: str, *, panel: str, scan_alpha: float) -> None:
    """The ``panel`` (before; after and slots: with the push paths; slots: truth not labelled),
    its parts' SVG ids prefixed with its name."""
    from matplotlib.patches import Polygon


    if rev.scan is not None:
        _ground(ax, rev.scan, scan_alpha, f"{panel}-full-scan")
    if rev.layout is not None:
        w, h = rev.layout.area
        ax.plot([0, w, w, 0, 0], [0, 0, h, h, 0], color="0.6", lw=0.8)
        for k in rev.layout.regions:
            ax.add_patch(Polygon(k.polygon, closed=True, fc=(1, 0.3, 0.3, 0.15), ec="tab:red", lw=0.8))
        for tg in rev.layout.targets:
            outline(ax, tg, ec=SLOT, ls="-", lw=1.2, gid=f"{panel}-slot-{tg.id}")
            _label(ax, tg, tg.id, SLOT, "lower left", f"{panel}-slot-label-{tg.id}", fontweight="bold")
    for b in truth:
        outline(ax, b, ec=TRUTH, ls=":", lw=1.0, gid=f"{panel}-truth-{b.id}", zorder=2)
        if panel != "slots":
            _label(ax, b, f"truth: scene id {b.id}", TRUTH, "lower right", f"{panel}-truth-label-{b.id}",
                   fontsize=5)
    for b in bodies:
        outline(ax, b, ec=OBJECT, ls="-", lw=0.8, fc=OBJECT_FILL, gid=f"{panel}-object-{b.id}")
        _label(ax, b, b.id, OBJECT, "upper right", f"{panel}-object-label-{b.id}")
    if panel != "before":
        for pts, verdict in rev.paths:
            if len(pts) >= 2:
                xs, ys = zip(*((p[0], p[1]) for p in pts))
                colour = "tab:red" if verdict in FAILED_VERDICTS else "tab:green"
                ax.plot(xs, ys, color=colour, lw=1.0)
                ax.plot(xs[-1], ys[-1], marker=".", color=colour)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x, nm")
    ax.set_ylabel("y, nm")


def _slots_region(ax, rev, title: str) -> None:
    """The after panel again, around the slots (their bounding box and a margin)."""
    if rev.layout is None or not rev.layout.targets:
        ax.axis("off")
        return
    _scene(ax, rev, rev.final, rev.truth_final, title, panel="slots", scan_alpha=0.25)
    boxes = np.array([t.bounds() for t in rev.layout.targets])
    (x0, y0), (x1, y1) = boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)
    margin = max(0.15 * max(x1 - x0, y1 - y0), 2.0 * max(t.diameter for t in rev.layout.targets))
    ax.set_xlim(x0 - margin, x1 + margin)
    ax.set_ylim(y0 - margin, y1 + margin)


def _ground(ax, image, alpha: float, gid: str) -> None:
    """The full scan, levelled, in grey under everything (at most :data:`SHOWN_PIXELS` a side)."""
    z, px, _ = levelled(image, SHOWN_PIXELS)
    lo, hi = np.nanpercentile(z, [1.0, 99.5]) if np.isfinite(z).any() else (0.0, 1.0)
    ny, nx = z.shape
    x0, y0 = image.origin
    ax.imshow(z, origin="lower", extent=(x0, x0 + nx * px, y0, y0 + ny * px), cmap="Greys", alpha=alpha,
              vmin=lo, vmax=max(hi, lo + 1e-6), interpolation="nearest", zorder=0, gid=gid)


_CORNERS = {"upper right": (2, 3, (1, 1), "left", "bottom"), "lower left": (0, 1, (-1, -1), "right", "top"),
            "lower right": (2, 1, (1, -1), "left", "top")}


def _label(ax, body, text: str, colour, corner: str, gid: str, **style) -> None:
    """``text`` beside ``body``'s bounding box at ``corner``, on a light box."""
    ix, iy, offset, ha, va = _CORNERS[corner]
    bounds = body.bounds()
    style.setdefault("fontsize", 6)
    ax.annotate(text, (bounds[ix], bounds[iy]), xytext=offset, textcoords="offset points", ha=ha, va=va,
                color=colour, gid=gid, zorder=4, bbox={"boxstyle": "square,pad=0.1", "fc": "white", "ec": "none",
                                                           "alpha": 0.6}, **style)


# -- slot errors, zoomed -----------------------------------------------------------------

def _zooms(fig, axes, rev) -> None:
    """On ``axes``, a panel for each of the slots with the largest errors, or a line saying there is none."""
    rows = sorted((s for s in rev.slots if s.error is not None and s.pose is not None), key=lambda s: -s.error)
    rows = rows[:ZOOMED] if rev.layout is not None else []
    for ax, row in zip(axes, rows):
        _zoom(ax, rev, row)
    for ax in axes[len(rows):]:
        ax.axis("off")
    if not rows:
        axes[0].text(0.0, 0.5, "no slot error to zoom on (no slot assigned with a known pose)",
                     transform=axes[0].transAxes, fontsize=10)
        return
    tol = rev.layout.tolerance.position
    fig.suptitle(f"around the slots (left), and the {len(rows)} largest slot error(s) against the {rev.source} "
                 f"zoomed: outlines at true "
                 f"scale; the error vector (red) and the {tol:g} nm position tolerance (dashed circle) magnified "
                 f"by the panel's factor", fontsize=10)


def _zoom(ax, rev, row) -> None:
    """One slot at true scale, its error vector and tolerance circle magnified."""
    from matplotlib.patches import Circle


    tg, pose = rev.layout.target(row.target), row.pose
    tol = rev.layout.tolerance.position
    x0, y0, x1, y1 = tg.bounds()
    half = max(0.75 * max(x1 - x0, y1 - y0) + 2.0 * tol, row.error + pose.radius + tol)
    gain = _gain(0.8 * half / max(row.error, tol))
    believed = {b.id: b for b in rev.final}.get(row.object) if row.truth is not None else None
    outline(ax, tg, ec=SLOT, lw=1.2)
    outline(ax, pose, ec=TRUTH if row.truth is not None else OBJECT, lw=1.0, fc=(1.0, 0.8, 0.2, 0.35))
    ax.add_patch(Circle(tg.at, gain * tol, fc="none", ec=SLOT, ls="--", lw=0.8))
    if believed is not None:
        outline(ax, believed, ec=OBJECT, ls="--", lw=0.8)
        _vector(ax, tg.at, believed.at, gain, "0.4", f"belief-error-{tg.id}")
    _vector(ax, tg.at, pose.at, gain, ERROR, f"error-{tg.id}")
    ax.set_xlim(tg.at[0] - half, tg.at[0] + half)
    ax.set_ylim(tg.at[1] - half, tg.at[1] + half)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    ax.set_gid(f"zoom-{tg.id}")
    turn = f", {axis_error(pose.angle, tg.angle):.1f}°" if tg.kind == "rod" and pose.kind == "rod" else ""
    ax.set_title(f"slot {tg.id}: {row.error:.1f} nm{turn} off\n{'filled' if row.filled else 'missed'} by "
                 f"{row.object}; vectors x{gain:g}", fontsize=8)
    if row.truth is not None:
        ax.text(0.02, 0.02, f"truth: scene id {row.truth}", transform=ax.transAxes, fontsize=6, color=TRUTH)


def _gain(most: float) -> float:
    """A round magnification no larger than ``most`` (an integer below 10, then 1-2-5 steps), at least 1."""
    if most < 10.0:
        return float(max(1, math.floor(most)))
    decade = 10.0 ** math.floor(math.log10(most))
    return max(m * decade for m in (1.0, 2.0, 5.0) if m * decade <= most)


def _vector(ax, start, end, gain: float, colour, gid: str) -> None:
    """The arrow from ``start`` to ``end`` magnified ``gain`` times about ``start``."""
    from matplotlib.patches import FancyArrowPatch

    tip = (start[0] + gain * (end[0] - start[0]), start[1] + gain * (end[1] - start[1]))
    ax.add_patch(FancyArrowPatch(start, tip, arrowstyle="-|>", mutation_scale=10, color=colour, lw=1.2,
                                 shrinkA=0, shrinkB=0, zorder=5, gid=gid))


# -- drift -------------------------------------------------------------------------------

def _drift(ax, rev) -> None:
    """The drift estimate over time (±σ) and, in a dry-run, the truth beside it."""
    ax.set_gid("drift")
    if not rev.drift:
        ax.text(0.5, 0.5, "no drift estimate in the log", ha="center", va="center", transform=ax.transAxes)
    t = [r[0] / 60 for r in rev.drift]
    true_t = [r[0] / 60 for r in rev.true_drift]
    for i, (axis, colour) in enumerate((("x", "tab:blue"), ("y", "tab:orange"))):
        if rev.drift:
            v = [r[1 + i] for r in rev.drift]
            s = [r[3 + i] for r in rev.drift]
            ax.plot(t, v, color=colour, label=f"d{axis} estimate", gid=f"drift-{axis}")
            if not all(math.isnan(x) for x in s):
                ax.fill_between(t, [a - b for a, b in zip(v, s)], [a + b for a, b in zip(v, s)],
                                color=colour, alpha=0.25, label=f"d{axis} +/- sigma")
        if rev.true_drift:
            ax.plot(true_t, [r[1 + i] for r in rev.true_drift], color=colour, ls="--", marker=".", ms=3,
                    label=f"d{axis} true", gid=f"true-drift-{axis}")
    if rev.drift or rev.true_drift:
        ax.legend(fontsize=8)
    ax.set_xlabel("instrument time, min")
    ax.set_ylabel("drift since the run's start, nm")
    off = rev.last_drift_error()
    ax.set_title("drift estimate" + ("" if not rev.true_drift else " and the true drift (dashed)") +
                 ("" if off is None else f"\nthe last estimate is {off:.1f} nm from the truth"), fontsize=10)

