"""Pictures for ``identify --plot FILE`` and ``plan --plot FILE``: what was found, what will be done.

:func:`identify_figure` draws the levelled scan (heights in nm, a colour bar, axes in nm
in the environment's frame) with every identified object outlined and labelled with its
id: particles as discs, rods and wires as capsules, obstacles hatched, anything cut by
the scan's border dashed. :func:`plan_figure` draws the same ground (the scan when there
is one) with the layout's slots and keep-outs in the scan's frame (registered by its
marks when it was), a line from each assigned object to its slot and every push's tip
path, numbered in order and coloured by object. :func:`write_figure` writes either
atomically, in the format of the file's suffix (:data:`SUFFIXES`).

Every outline carries an SVG id (``object-o3``, ``obstacle-2``, ``slot-s1``,
``assign-s1``, ``push-7``) and text stays text in SVG, so a picture can be checked.
Figures are plain :class:`matplotlib.figure.Figure` s: no pyplot, no GUI backend.
"""

from __future__ import annotations

import io
import math
import os
from collections import Counter

import numpy as np

from nanoasm.errors import InputError

#: Suffixes of a picture (the format is the suffix's).
SUFFIXES = (".png", ".svg", ".pdf")
#: Outline colour of each kind of identified object (on the dark scan).
COLOURS = {"particle": "cyan", "rod": "lime", "wire": "magenta"}
OBSTACLE, SLOT, UNFILLED, KEEPOUT = "red", "white", "orangered", "orange"
BACKGROUND = "0.12"
#: What the label of an object cut by the scan's border ends in.
EDGE = " (edge)"
#: The most pixels a side of the scan is drawn with: a larger scan is drawn by the highest
#: pixel of each block, so that no object drops out of the picture.
SHOWN_PIXELS = 1024


def check_plot_path(path: os.PathLike | None) -> None:
    """Refuse (one line) a picture whose suffix names no format we write."""
    if path is not None and os.path.splitext(str(path))[1].lower() not in SUFFIXES:
        raise InputError(str(path), None, "plot must end in .png, .svg or .pdf")


def _axes(area, image=None):
    """A figure and its axes over ``area`` (nm), with the levelled ``image`` under it
    when given (else a dark ground like a bare substrate's)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 8.0))
    ax = fig.add_subplot()
    w, h = area
    ax.set_facecolor(BACKGROUND)
    if image is not None:
        z, side, sigma = levelled(image)
        lo, hi = np.nanpercentile(z, [0.5, 99.8]) if np.isfinite(z).any() else (0.0, 1.0)
        lo = min(lo, 0.0)                   # the substrate dark, what rises 10 sigma above it clear
        shown = ax.imshow(z, origin="lower", extent=(0.0, z.shape[1] * side, 0.0, z.shape[0] * side),
                          cmap="afmhot", vmin=lo, vmax=max(hi, lo + 10.0 * sigma, lo + 1e-6),
                          interpolation="nearest")
        fig.colorbar(shown, ax=ax, shrink=0.8, label="height above the levelled substrate, nm")
    ax.plot([0, w, w, 0, 0], [0, 0, h, h, 0], color="0.6", lw=0.8)
    ax.set_xlim(0.0, w)
    ax.set_ylim(0.0, h)
    ax.set_aspect("equal")
    ax.set_xlabel("x, nm")
    ax.set_ylabel("y, nm")
    return fig, ax


def outline(ax, b, **style) -> None:
    """Body ``b`` (a particle, rod, slot or any :class:`~nanoasm.bodies.Body`) as its
    outline, a matplotlib patch (unfilled unless ``fc`` is given)."""
    from matplotlib.patches import Polygon

    ring = b.geometry().buffer(b.radius, quad_segs=8).exterior.coords
    style.setdefault("fc", "none")
    ax.add_patch(Polygon(list(ring), closed=True, **style))


def levelled(image, shown: int = SHOWN_PIXELS) -> tuple[np.ndarray, float, float]:
    """The scan levelled as identify levels it (NaN where it has no height), at most
    ``shown`` pixels a side (the highest of each block); the side of a pixel shown and
    the substrate's noise (sigma), nm."""
    from nanoasm.world.identify import level

    lev = level(image.height)
    z = np.where(lev.valid, lev.height, np.nan)
    step = math.ceil(max(z.shape) / shown)
    if step > 1:
        ny, nx = -(-z.shape[0] // step), -(-z.shape[1] // step)
        blocks = np.full((ny * step, nx * step), np.nan)
        blocks[:z.shape[0], :z.shape[1]] = z
        z = np.fmax.reduce(blocks.reshape(ny, step, nx, step), axis=(1, 3))
    return z, image.pixel_size * step, lev.sigma


def _environment(ax, env) -> list:
    """The identified objects (labelled) and obstacles; returns the legend's handles."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Polygon


    for k, ob in enumerate(env.obstacles, start=1):
        ax.add_patch(Polygon(ob.polygon, closed=True, fc="none", ec=OBSTACLE, hatch="//", lw=1.0,
                             ls="--" if ob.edge else "-", gid=f"obstacle-{k}"))
    for o in env.objects:
        colour = COLOURS[o.kind]
        outline(ax, o, ec=colour, lw=1.2, ls="--" if o.edge else "-", gid=f"object-{o.id}", zorder=3)
        ax.annotate(o.id + EDGE * o.edge, o.bounds()[2:], xytext=(1, 1), textcoords="offset points",
                    color=colour, fontsize=7, zorder=4)
    kinds = Counter(o.kind for o in env.objects)
    handles = [Line2D([], [], color=COLOURS[k], lw=1.5, label=f"{kinds[k]} {k}(s)") for k in COLOURS if kinds[k]]
    if env.obstacles:
        handles.append(Patch(fc="none", ec=OBSTACLE, hatch="//", label=f"{len(env.obstacles)} obstacle(s)"))
    edge = sum(o.edge for o in env.objects) + sum(ob.edge for ob in env.obstacles)
    if edge:
        handles.append(Line2D([], [], color="0.7", ls="--", label=f"{edge} cut by the border (dashed; never "
                                                                  "assigned)"))
    return handles


def _frame_note(env) -> str:
    x, y = env.origin
    return "" if (x, y) == (0.0, 0.0) else f"; (0, 0) is the scan file's ({x:g}, {y:g}) nm"


def _legend(ax, handles: list) -> None:
    if handles:
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=3, fontsize=8,
                  facecolor=BACKGROUND, edgecolor=BACKGROUND, labelcolor="white", framealpha=1.0)


def identify_figure(image, env, name: str = "scan"):
    """The levelled ``image`` (a HeightImage) with what identification found in it (``env``)."""
    fig, ax = _axes(env.area, image)
    _legend(ax, _environment(ax, env))
    ax.set_title(f"{name}: {len(env.objects)} object(s), {len(env.obstacles)} obstacle(s) identified"
                 f"{_frame_note(env)}", fontsize=10)
    return fig


def plan_figure(layout, env, plan, image=None):
    """The plan: slots of ``layout`` (in the scan's frame), the objects and obstacles of
    ``env`` (over the levelled ``image`` when given), assignments and pushes."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Polygon


    fig, ax = _axes(env.area, image)
    handles = _environment(ax, env)
    for k, region in enumerate(layout.regions, start=1):
        ax.add_patch(Polygon(region.polygon, closed=True, fc="none", ec=KEEPOUT, hatch="\\\\", lw=1.0,
                             gid=f"keepout-{k}"))
    unfilled = {u.target for u in plan.unfilled}
    for t in layout.targets:
        colour = UNFILLED if t.id in unfilled else SLOT
        outline(ax, t, ec=colour, lw=1.4, ls="-." if t.id in unfilled else "-", gid=f"slot-{t.id}", zorder=3)
        ax.annotate(t.id, t.at, xytext=(-4, -4), textcoords="offset points", ha="right", va="top",
                    color=colour, fontsize=7, fontweight="bold", zorder=4)
    objects = {o.id: o for o in env.objects}
    for a in (a for a in plan.assignment if a.object in objects):
        (x0, y0), (x1, y1) = objects[a.object].at, layout.target(a.target).at
        ax.plot([x0, x1], [y0, y1], color=SLOT, lw=0.8, ls=":", gid=f"assign-{a.target}", zorder=2)
    _pushes(ax, plan.operations)
    handles += [Line2D([], [], color=SLOT, lw=1.4, label=f"{len(layout.targets)} slot(s)"),
                Line2D([], [], color=SLOT, lw=0.8, ls=":", label="object to slot"),
                Line2D([], [], color="0.5", marker=">", label=f"{len(plan.operations)} push(es), numbered")]
    if unfilled:
        handles.append(Line2D([], [], color=UNFILLED, ls="-.", label=f"{len(unfilled)} slot(s) unfilled"))
    if layout.regions:
        handles.append(Patch(fc="none", ec=KEEPOUT, hatch="\\\\", label="keep-outs and marks"))
    _legend(ax, handles)
    reg = layout.registration
    frame = "" if reg is None else f"\nlayout registered by its marks: {reg.line()}"
    ground = "over the scan" if image is not None else "(no scan: the environment only)"
    ax.set_title(f"plan of {layout.name or 'layout'}: {len(plan.assignment)} of {len(layout.targets)} slot(s) "
                 f"assigned, {len(plan.operations)} push(es) {ground}{_frame_note(env)}{frame}", fontsize=10)
    return fig


def _pushes(ax, operations) -> None:
    """Each push's tip path with an arrow head, coloured by object, numbered at its start."""
    from matplotlib import colormaps

    palette = colormaps["tab10"].colors
    order = {oid: i for i, oid in enumerate(dict.fromkeys(op.object for op in operations))}
    for op in operations:
        colour = palette[order[op.object] % len(palette)]
        xs, ys = zip(*op.tip_path)
        ax.plot(xs, ys, color=colour, lw=1.0, gid=f"push-{op.id}", zorder=5)
        ax.annotate("", xy=op.tip_path[-1], xytext=op.tip_path[-2], zorder=5,
                    arrowprops=dict(arrowstyle="-|>", color=colour, lw=1.0, shrinkA=0, shrinkB=0))
        ax.annotate(str(op.id), op.tip_path[0], xytext=(-3, 3), textcoords="offset points", ha="right",
                    color=colour, fontsize=6, zorder=5)


def write_figure(fig, out: os.PathLike) -> None:
    """Write ``fig`` to ``out`` in its suffix's format, atomically (complete or absent)."""
    import matplotlib

    from nanoasm.fileio import write_atomic

    buf = io.BytesIO()
    fmt = os.path.splitext(str(out))[1].lstrip(".").lower()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "nanoasm"}):
        fig.savefig(buf, format=fmt, dpi=120, bbox_inches="tight", metadata=_metadata(fmt))
    write_atomic(out, buf.getvalue())


def _metadata(fmt: str) -> dict:
    """No creation date in the file, so that the same input gives the same picture."""
    return {"png": {"Software": None}, "svg": {"Date": None}, "pdf": {"CreationDate": None}}.get(fmt, {})
