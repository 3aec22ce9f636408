"""Particles the check scans find in their slot only near the edge of its tolerance:
pushed towards the slot's centre again before the verdict stands.

A check scan measures a slot's centre error to within a few nanometres: its lines' fit
and the drift estimate's uncertainty at the time. A particle measured 19.9 nm from the
centre of a slot of 20 nm tolerance is filled or missed by the toss of that measurement
(``scale1000`` seed 2: slot s173's particle, measured 19.87 nm off, lay 21.3 nm off in the
simulated truth, and the report called the slot filled). A report cannot stand by such a
verdict, and the push that settles it is short. So a particle slot the check scans find
filled, but farther from its centre than the tighter tolerance the run's own
corrections aim for (:func:`~.course.tight`, 0.6 of the layout's), has its particle
pushed towards the centre again in a repair round (:mod:`.repair`; one such push per
particle and round, planned as the run's corrections are), and only those slots are
checked again. Rod slots are left to the rod's course.
"""

from __future__ import annotations

from nanoasm.cad.layout import Layout
from nanoasm.planner import Operation, PlanOptions

from .context import RunContext
from .course import correction, tight


def edge_slots(layout: Layout, verdicts, ctx: RunContext) -> list:
    """(target, verdict) of the particle slots ``verdicts`` call filled whose measured
    error is beyond :func:`~.course.tight`'s position tolerance, their particle believed,
    not lost and not given up."""
    near = tight(layout).position
    b = ctx.belief
    return [(t, v) for t, v in zip(layout.targets, verdicts)
            if t.kind == "particle" and v.state == "filled" and v.error is not None and v.error > near
            and v.object in b.objects and v.object not in b.lost and v.object not in ctx.ledger.given_up]


def edge_pushes(layout: Layout, ctx: RunContext, edge, options: PlanOptions, first_id: int) -> list[Operation]:
    """The pushes that bring the particles of the slots ``edge`` (:func:`edge_slots`) to
    within the tight tolerance of their centres, numbered from ``first_id``: each a
    single-object plan from the belief the check scans left (:func:`~.course.correction`),
    none for a particle the belief already has there."""
    ops: list[Operation] = []
    for target, v in edge:
        extra = correction(layout, ctx.belief, target.id, v.object, {}, 1, options, first_id + len(ops))
        ops += extra or []
    return ops


def edge_line(edge, n_pushes: int) -> str:
    """The event that names the slots of ``edge`` and the pushes they take."""
    worst = max(v.error for _, v in edge)
    return (f"{len(edge)} slot(s) filled only near the edge of the tolerance (up to {worst:.1f} nm "
            f"off: {', '.join(t.id for t, _ in edge)}): {n_pushes} push(es) to bring their particles in")

