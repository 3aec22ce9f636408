"""Objects to slots: compatible pairs only, least total effort, reasons for the rest.

Objects already in a slot within tolerance stay there. The others are matched by
``scipy.optimize.linear_sum_assignment`` over compatible pairs (same kind, size within
``tolerance.size``, rods with σ below the rod limit), cost = estimated effort.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout, Tolerance, size_ok
from nanoasm.world.environment import EnvObject

from .options import PlanOptions
from .plan import Unfilled

#: Cost of an incompatible pair; such pairs are dropped after the matching.
_FORBIDDEN = 1e18


@dataclass(frozen=True)
class Matching:
    """``moves``: (target, object) pairs to push; ``staying``: already in their slot."""

    moves: tuple[tuple[str, str], ...]
    staying: tuple[tuple[str, str], ...]
    unfilled: tuple[Unfilled, ...]


def axis_error(a: float, b: float) -> float:
    """Smallest difference of two axis angles (degrees, modulo 180), in [0, 90]."""
    d = (a - b) % 180.0
    return min(d, 180.0 - d)


def assignable(obj: EnvObject, options: PlanOptions) -> bool:
    """Objects that may be pushed into a slot at all."""
    if obj.edge or obj.confidence < options.min_confidence or obj.kind == "wire":
        return False
    return obj.kind == "particle" or obj.aspect < options.rod_limit


def compatible(target: Body, obj: EnvObject, tol: Tolerance) -> bool:
    return obj.kind == target.kind and size_ok(target, obj, tol)


def in_slot(target: Body, obj: Body, tol: Tolerance) -> bool:
    """The slot-filled rule of the report format."""
    if obj.kind != target.kind or not size_ok(target, obj, tol):
        return False
    if math.dist(obj.at, target.at) > tol.position:
        return False
    return target.kind != "rod" or axis_error(obj.angle, target.angle) <= tol.angle


def effort(target: Body, obj: Body) -> float:
    """Estimated push effort, nm: centre travel plus, for rods, the arc the ends sweep."""
    cost = math.dist(obj.at, target.at)
    if target.kind == "rod":
        cost += math.radians(axis_error(obj.angle, target.angle)) * target.length
    return cost


def _columns(bodies: Sequence[Body]) -> dict[str, np.ndarray]:
    rod = np.array([b.kind == "rod" for b in bodies])
    return {
        "rod": rod,
        "xy": np.array([b.at for b in bodies], dtype=float).reshape(-1, 2),
        "d": np.array([b.diameter for b in bodies], dtype=float),
        "L": np.array([b.length if b.kind == "rod" else 0.0 for b in bodies], dtype=float),
        "angle": np.array([b.angle if b.kind == "rod" else 0.0 for b in bodies], dtype=float),
    }


def effort_matrix(targets: Sequence[Body], objects: Sequence[Body], tol: Tolerance) -> np.ndarray:
    """(T, O) array of :func:`effort`, ``_FORBIDDEN`` where the pair is incompatible."""
    t, o = _columns(targets), _columns(objects)
    ok = t["rod"][:, None] == o["rod"][None, :]
    ok &= np.abs(o["d"][None, :] - t["d"][:, None]) <= tol.size * t["d"][:, None]
    ok &= ~t["rod"][:, None] | (np.abs(o["L"][None, :] - t["L"][:, None]) <= tol.size * t["L"][:, None])
    cost = np.hypot(*(t["xy"][:, None, :] - o["xy"][None, :, :]).transpose(2, 0, 1))
    turn = np.abs(o["angle"][None, :] - t["angle"][:, None]) % 180.0
    turn = np.minimum(turn, 180.0 - turn)
    cost = cost + np.where(t["rod"][:, None], np.radians(turn) * t["L"][:, None], 0.0)
    return np.where(ok, cost, _FORBIDDEN)


def _near(pool: Sequence[Body], points, reach: float) -> list[list[int]]:
    """For each of ``points``, the indices of the bodies of ``pool`` whose centre may lie
    within ``reach`` of it (a k-d tree's ball, a hair wider: :func:`in_slot` decides);
    every slot against every object was 39 million tests in a 1000-object run."""
    if not pool or not len(points):
        return [[] for _ in points]
    tree = cKDTree(np.array([b.at for b in pool], float).reshape(-1, 2))
    return tree.query_ball_point(np.asarray(points, float).reshape(-1, 2), reach * (1 + 1e-9) + 1e-9)


def describe(target: Body, tol: Tolerance) -> str:
    pct = f"{tol.size * 100:g}%"
    if target.kind == "rod":
        return f"rod of length {target.length:g} and diameter {target.diameter:g} +/- {pct}"
    return f"particle of diameter {target.diameter:g} +/- {pct}"


def match(layout: Layout, objects: Sequence[EnvObject], options: PlanOptions,
          held: Sequence[EnvObject] = ()) -> Matching:
    """Assign objects to the layout's slots. ``held``: objects that lie there but may not
    be pushed (given up by a run, cut by the scan's edge, unsure, a rod on a keep-out); a
    slot that no object fits says so when some of them would."""
    tol = layout.tolerance
    pool = [o for o in objects if assignable(o, options)]
    staying: list[tuple[str, str]] = []
    taken: set[str] = set()
    open_targets = []
    near = _near(pool, [t.at for t in layout.targets], tol.position)
    for t, ks in zip(layout.targets, near):
        inside = sorted((math.dist(pool[k].at, t.at), pool[k].id) for k in ks
                        if pool[k].id not in taken and in_slot(t, pool[k], tol))
        if inside:
            staying.append((t.id, inside[0][1]))
            taken.add(inside[0][1])
        else:
            open_targets.append(t)
    free = [o for o in pool if o.id not in taken]

    moves: list[tuple[str, str]] = []
    if open_targets and free:
        cost = effort_matrix(open_targets, free, tol)
        rows, cols = linear_sum_assignment(cost)
        for i, j in zip(rows, cols):
            if cost[i, j] < _FORBIDDEN:
                moves.append((open_targets[i].id, free[j].id))
    assigned = {t for t, _ in moves}

    unfilled = []
    for t in open_targets:
        if t.id in assigned:
            continue
        n = sum(compatible(t, o, tol) for o in pool)
        if n == 0:
            reason = f"no {describe(t, tol)}"
            ids = [o.id for o in held if compatible(t, o, tol)]
            if ids:
                some = ", ".join(repr(i) for i in ids[:3]) + (f" and {len(ids) - 3} more" if len(ids) > 3 else "")
                reason += (f" that may be pushed ({some} may not: given up, at the scan's edge, unsure "
                           f"or on a keep-out)")
        else:
            reason = f"all {n} compatible {t.kind}s are used by other slots"
        unfilled.append(Unfilled(t.id, reason))
    return Matching(tuple(moves), tuple(staying), tuple(unfilled))
