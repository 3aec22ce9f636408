"""Where each rod really turns: its pivot offset, learnt push by push (issue 14).

The pivot model (seed eq. 4.10) puts a pushed rod's pivot at s(l) from the pushed end. A
friction gradient along a real rod moves it along the axis by δ·L; a 30 % gradient moves
it by about 0.015 L. Unknown, δ = 0.03 costs about 8 nm at the far end per push.

A push turns the rod about its pivot, so a pivot moved by δ·L moves the rod's centre by
about ``δ L · 2 sin(β/2)`` across for a turn β (a 10° swing of a 1300 nm rod with δ = 0.03:
7 nm). Every rod pushed keeps an extended Kalman filter over its pose and δ: a push is
the prediction (the pivot model with δ, linearised by finite differences), each scan
of the rod (before and after every push) an update of the pose. The pose's scan errors
are carried from one push to the next, so the after-scan of one push and the before-scan
of the next are not counted as independent evidence. The prior on δ is the scatter seen
in rods of its aspect ratio.

``δ`` is signed along the executor's own axis direction (its ``angle``), which the belief
keeps continuous over a run, so the estimate refers to the same physical end throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.bodies import Body
from nanoasm.planner.rods import simulate_push

#: Prior standard deviation of δ (fraction of L) for a rod, and its factor for rods of
#: 15 <= L/d <= 25, whose pivot the model places with less confidence (seed §4.3.1).
PRIOR_STD = 0.03
UNCERTAIN_GAIN = 3.0
#: The estimate is kept within this (fraction of L): beyond it the pivot leaves the model.
LIMIT = 0.3
#: Angle 1σ (degrees) of a rod pose whose scan gave none.
ANGLE_STD = 0.5
#: What the pivot model leaves out of one push, 1σ: centre (nm), angle (degrees) and the
#: pivot offset itself (fraction of L: the friction under a rod changes as it moves, and the
#: model's pivot is not exactly the world's; without it the filter claimed ±0.001 after 40
#: pushes of a rods-family rod while its error was 0.001-0.009).
PUSH_STD = (1.0, 0.2, 0.002)
#: Squared Mahalanobis distance (3 degrees of freedom, 1 in 10⁴ by chance) beyond which a
#: scan says the rod met something the model does not know: the pose starts again from
#: the scan, δ keeps what was learnt.
GATE = 21.1
#: Step in δ of the finite-difference Jacobian.
EPS = 0.002


def prior_std(length: float, diameter: float) -> float:
    """Prior 1σ of δ for a rod of ``length`` and ``diameter`` (nm)."""
    aspect = length / diameter
    return PRIOR_STD * (UNCERTAIN_GAIN if 15.0 <= aspect <= 25.0 else 1.0)


def _pose(b: Body) -> np.ndarray:
    return np.array([b.at[0], b.at[1], b.angle], float)


def _meas_cov(cov, angle_std: float) -> np.ndarray:
    r = np.zeros((3, 3))
    r[:2, :2] = np.asarray(cov, float)
    r[2, 2] = angle_std ** 2
    return r


@dataclass
class RodTrack:
    """One rod's filter: ``mean`` = (x, y, angle, δ) in nm, degrees and fractions of L,
    ``cov`` its 4x4 covariance; ``pushes`` the pushes folded in."""

    rod: Body
    mean: np.ndarray
    cov: np.ndarray
    pushes: int = 0

    @property
    def offset(self) -> float:
        return float(self.mean[3])

    @property
    def std(self) -> float:
        return math.sqrt(max(float(self.cov[3, 3]), 0.0))

    def body(self) -> Body:
        x, y, a, _ = self.mean
        return Body(self.rod.id, "rod", (float(x), float(y)), self.rod.diameter, float(a), self.rod.length)

    def to_dict(self) -> dict:
        """For the run log: δ, its 1σ, the pushes folded in, and the axis angle (degrees)
        whose direction δ is measured along."""
        return {"offset": self.offset, "std": self.std, "pushes": self.pushes, "angle": float(self.mean[2])}


class Pivots:
    """The pose-and-pivot filter of every rod pushed so far."""

    def __init__(self) -> None:
        self.rods: dict[str, RodTrack] = {}

    def get(self, rod: Body) -> RodTrack:
        """``rod``'s filter, started from its pose (covariance unknown: 1 nm, 1°) and the prior."""
        tr = self.rods.get(rod.id)
        if tr is None:
            cov = np.diag([1.0, 1.0, 1.0, prior_std(rod.length, rod.diameter) ** 2])
            tr = self.rods[rod.id] = RodTrack(rod, np.array([*_pose(rod), 0.0]), cov)
        return tr

    def offsets(self, objects) -> dict[str, float]:
        """The learnt offsets of the rods among ``objects`` (bodies), each signed along that
        body's own ``angle`` (which may point the other way along the axis)."""
        out = {}
        for o in objects:
            tr = self.rods.get(o.id)
            if tr is not None and o.angle is not None:
                flip = math.cos(math.radians(o.angle) - math.radians(float(tr.mean[2]))) < 0.0
                out[o.id] = -tr.offset if flip else tr.offset
        return out

    def seen(self, rod: Body, cov, angle_std: float = ANGLE_STD) -> RodTrack:
        """A scan found the rod at ``rod`` (pose; ``cov`` 2x2 nm²): update its filter. A scan
        far outside the prediction (:data:`GATE`) restarts the pose from it."""
        tr = self.get(rod)
        z, r = _pose(rod), _meas_cov(cov, angle_std)
        y = z - tr.mean[:3]
        y[2] = math.remainder(y[2], 180.0)
        s = tr.cov[:3, :3] + r
        try:
            d2 = float(y @ np.linalg.solve(s, y))
        except np.linalg.LinAlgError:
            d2 = math.inf
        if not d2 <= GATE:
            return self.restart(rod, cov, angle_std)
        k = np.linalg.solve(s, tr.cov[:3, :]).T                  # 4x3 gain
        tr.mean = tr.mean + k @ y
        tr.cov = tr.cov - k @ tr.cov[:3, :]
        tr.cov = 0.5 * (tr.cov + tr.cov.T)
        tr.mean[3] = float(np.clip(tr.mean[3], -LIMIT, LIMIT))
        return tr

    def restart(self, rod: Body, cov, angle_std: float = ANGLE_STD) -> RodTrack:
        """The rod's pose starts again from a scan (``rod``, ``cov``); δ keeps what was
        learnt. The angle stays on the filter's side of the axis, so δ's sign keeps
        referring to the same end."""
        tr = self.get(rod)
        z = _pose(rod)
        z[2] = tr.mean[2] + math.remainder(z[2] - tr.mean[2], 180.0)
        tr.mean[:3] = z
        tr.cov[:3, :] = 0.0
        tr.cov[:, :3] = 0.0
        tr.cov[:3, :3] = _meas_cov(cov, angle_std)
        return tr

    def pushed(self, rod_id: str, tip_path, tip_radius: float) -> Body:
        """The rod was pushed along ``tip_path`` (its frame): predict its pose by the pivot
        model with the estimated δ; returns the predicted pose."""
        tr = self.rods[rod_id]
        t0, t1 = tip_path[0], tip_path[-1]
        m = tr.mean

        def f(v: np.ndarray) -> np.ndarray:
            b = Body(rod_id, "rod", (float(v[0]), float(v[1])), tr.rod.diameter, float(v[2]), tr.rod.length)
            return _pose(simulate_push(b, t0, t1, tip_radius, pivot_offset=float(v[3])))

        f0 = f(m)
        jac = np.zeros((3, 4))
        steps = (0.5, 0.5, 0.05, EPS)
        for i, h in enumerate(steps):
            e = np.zeros(4)
            e[i] = h
            d = f(m + e) - f0
            d[2] = math.remainder(d[2], 180.0)
            jac[:, i] = d / h
        big_f = np.eye(4)
        big_f[:3, :] = jac
        q = np.diag([PUSH_STD[0] ** 2, PUSH_STD[0] ** 2, PUSH_STD[1] ** 2, PUSH_STD[2] ** 2])
        tr.mean = np.array([*f0, m[3]])
        tr.cov = big_f @ tr.cov @ big_f.T + q
        tr.pushes += 1
        return tr.body()

    def state_dict(self) -> dict:
        return {k: {"length": v.rod.length, "diameter": v.rod.diameter, "mean": v.mean.tolist(),
                    "cov": v.cov.tolist(), "pushes": v.pushes} for k, v in self.rods.items()}

    @classmethod
    def from_state(cls, state: dict | None) -> Pivots:
        out = cls()
        for k, v in (state or {}).items():
            mean = np.asarray(v["mean"], float)
            rod = Body(str(k), "rod", (float(mean[0]), float(mean[1])), float(v["diameter"]), float(mean[2]),
                       float(v["length"]))
            out.rods[str(k)] = RodTrack(rod, mean, np.asarray(v["cov"], float), int(v.get("pushes", 0)))
        return out
