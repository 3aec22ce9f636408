"""The last pushes of a rod into its slot, by a receding horizon (issue 14).

Near its slot a rod needs a few pushes whose swings trade position against angle: the
pivot model makes each push a rotation by φ about the pivot of eq. 4.10 for the push
point (moved by the rod's pivot offset δ·L), so after a push near end ``e`` the centre
is ``c' = c + p (u(θ) − u(θ + φ))`` and the angle ``θ + φ``, with ``p = e (L/2 − s) + δ L``
the pivot's place along the axis from the centre and ``u`` the axis direction. For a
sequence of ends (each of the 2^K of a horizon of K pushes), casadi's ``Opti`` with ipopt
finds the swings that bring the pose closest to the slot (position and angle scaled by
their tolerances) at the least swing; the shortest horizon that reaches the slot wins,
else the best four-push plan's first push is made and the horizon moves on from the
pose the full model (:func:`~nanoasm.planner.rods.simulate_push`) predicts for it.
Distances in µm and angles in radians inside the problem (ipopt is poorly scaled in nm).

This replaces a greedy choice among a fixed library of small swings, which needs many
pushes for an error along the rod's axis (a few nm a push) and oscillates about the slot.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import casadi
import numpy as np

from nanoasm.bodies import Body
from nanoasm.world.pivot import pivot_position

#: Longest horizon, pushes (2^4 sequences of ends at the longest).
HORIZON = 4
#: Weight of the swings (per rad², against errors in units of the tolerance).
SWING_WEIGHT = 0.05
#: A plan ends within this share of the tolerances (margin for the model's error).
MARGIN = 0.5

_SOLVERS: dict[int, Callable] = {}


def _solver(k: int):
    """A compiled problem for every sequence of ends of a horizon of ``k`` pushes at once
    (the 2^k problems are independent, so one ipopt call solves them together):
    parameters (x, y, θ, gx, gy, gθ, position and angle scales, swing limit) and the
    pivot places ``(k, 2^k)``; decisions the swings ``(k, 2^k)``; outputs the swings and
    each sequence's cost."""
    if k in _SOLVERS:
        return _SOLVERS[k]
    n = 2 ** k
    opti = casadi.Opti()
    phi = opti.variable(k, n)
    par = opti.parameter(9)
    places = opti.parameter(k, n)
    gx, gy, gth, sp, sa, lim = par[3], par[4], par[5], par[6], par[7], par[8]
    costs = []
    for j in range(n):
        x, y, th = par[0], par[1], par[2]
        for i in range(k):
            p = places[i, j]
            x = x + p * (casadi.cos(th) - casadi.cos(th + phi[i, j]))
            y = y + p * (casadi.sin(th) - casadi.sin(th + phi[i, j]))
            th = th + phi[i, j]
        costs.append(((x - gx) ** 2 + (y - gy) ** 2) / sp ** 2 + (th - gth) ** 2 / sa ** 2
                     + SWING_WEIGHT * casadi.sumsqr(phi[:, j]))
    cost = casadi.vertcat(*costs)
    opti.minimize(casadi.sum1(cost))
    opti.subject_to(opti.bounded(-lim, casadi.vec(phi), lim))
    opti.set_initial(phi, 0.01)
    opti.solver("ipopt", {"print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes",
                          "ipopt.max_iter": 200})
    fn = opti.to_function(f"rod_horizon_{k}", [par, places], [phi, cost])
    _SOLVERS[k] = fn
    return fn


def pivot_place(rod: Body, end: int, push_point: float, offset: float) -> float:
    """Where a push near ``end`` (−1: A, +1: B) at ``push_point`` of the length turns the rod:
    the pivot's place along the axis from the centre, nm."""
    L = rod.length
    s = float(pivot_position(push_point * L, L))
    return end * (L / 2 - s) + offset * L


def plan_swings(rod: Body, goal: Body, *, push_point: float, max_swing: float, pos_tol: float,
                ang_tol: float, offset: float = 0.0) -> list[tuple[float, list[tuple[int, float]]]]:
    """Plans from ``rod`` toward ``goal``, best first: ``(error, [(end, swing)])`` with the
    swing in degrees (signed) and the error the model predicts at the plan's end, in
    tolerances (:func:`_error`). The shortest horizon some plan of which reaches the slot
    (within ``MARGIN`` of the tolerances) gives whole plans; when none does, the longest
    horizon's plans are cut to their first push (the horizon moves on from where it
    leads). The caller takes the first plan that is free of collisions."""
    um = 1e-3
    th0 = math.radians(rod.angle)
    gth = th0 + math.radians(math.remainder(goal.angle - rod.angle, 180.0))
    base = [rod.at[0] * um, rod.at[1] * um, th0, goal.at[0] * um, goal.at[1] * um, gth,
            pos_tol * um, math.radians(ang_tol), math.radians(max_swing)]
    places = {e: pivot_place(rod, e, push_point, offset) * um for e in (-1, 1)}
    plans: list[tuple[float, list[tuple[int, float]]]] = []
    for k in range(1, HORIZON + 1):
        seqs = list(itertools.product((-1, 1), repeat=k))
        where = casadi.DM([[places[ends[i]] for ends in seqs] for i in range(k)])
        phi, _ = _solver(k)(casadi.DM(base), where)
        phi = np.asarray(phi).reshape(k, len(seqs))
        plans = []
        for j, ends in enumerate(seqs):
            pushes = [(e, math.degrees(float(phi[i, j]))) for i, e in enumerate(ends)]
            plans.append((_error(rod, goal, pushes, places, pos_tol, ang_tol), pushes))
        plans.sort(key=lambda p: p[0])
        if plans[0][0] <= MARGIN:
            return [p for p in plans if p[0] <= MARGIN]
    return [(err, pushes[:1]) for err, pushes in plans]


def _error(rod: Body, goal: Body, pushes: list[tuple[int, float]], places: dict, pos_tol: float,
           ang_tol: float) -> float:
    """The closed-form pose after ``pushes`` (``places`` in µm): its error against ``goal``
    in tolerances (the larger of position and angle: a plan is done when both are within)."""
    um = 1e-3
    x, y, th = rod.at[0] * um, rod.at[1] * um, math.radians(rod.angle)
    for e, sw in pushes:
        p, phi = places[e], math.radians(sw)
        x += p * (math.cos(th) - math.cos(th + phi))
        y += p * (math.sin(th) - math.sin(th + phi))
        th += phi
    return max(math.hypot(x - goal.at[0] * um, y - goal.at[1] * um) / (pos_tol * um),
               abs(math.degrees(math.remainder(th - math.radians(goal.angle), math.pi))) / ang_tol)
