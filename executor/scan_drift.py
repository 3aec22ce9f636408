"""The drift the first full scan's rows carried, as the bootstrap measures it.

A full scan takes minutes, one row after the other, while the sample drifts: what row
``i`` shows lies displaced by the drift ``D(τ_i)`` since the run's start (the layout
frame is the scanner frame then). Every position taken from the full scan (an object's,
a fixed feature's, a relocalisation window's) is put back by ``D(τ)``, for the whole
run; the drift filter's own state follows the drift as it goes on changing later.

The model over the scan is ``D(τ) = v τ + a τ²/2 + (1 + ε) creep(τ) + λ ∂creep/∂ln τ_c``: a velocity
``v`` that may change at a steady rate ``a`` (a drifting stage settles over hours: the
velocity changes by a few hundredths of nm/s in ten minutes), and the creep of the
scanner moves made before the scan ended (the drift filter's creep history folds old
moves into a constant valid only from then on, so these are kept apart), at an
amplitude known only to a relative error ``ε`` and a time constant ``τ_c`` known only
to a relative error ``λ = δ ln τ_c`` (a real scanner's each to some ±30 %). The creep of
the travels to the references scanned again is a few hundred nm on a wide area, so a
model without ``ε`` takes the error of its amplitude for velocity; and seconds after a
move ``s`` its creep is ``c s (log10 t − log10 τ_c)``, so an error of ``τ_c`` leaves an
offset ``c s λ / ln 10`` along every long travel (17 nm after 10 µm at λ = −0.34), which
a model without ``λ`` takes for velocity too: on wide seed 8 (τ_c 29 % short) the rows of
a 1600 s scan came out up to 13 nm apart from where they were. ``θ = (v, a, ε, λ)``
starts from a prior and is measured by Bayesian least squares: scanning a reference
again at ``t`` gives its component along ``n`` of ``D(t) − D(τ)`` (the creep at ``t`` of
every move so far), linear in ``θ`` (in ``λ`` too: ``∂creep/∂λ = c/ln 10 Σ s_i x_i/(1 +
x_i)``, ``x_i`` the time since move ``i`` in units of ``τ_c``); the drift filter then
carries ``ε`` as its learnt creep amplitude error and ``λ`` as a static of its state.
"""

from __future__ import annotations

import copy

import numpy as np

from nanoasm.drift.creep import creep_offset, creep_tau_sensitivity

#: Prior standard deviation of the steady change of the drift velocity, nm/s².
ACCELERATION_STD = 5e-5
#: The velocity is known when its standard deviation is below this in every direction, nm/s.
KNOWN_VELOCITY_STD = 0.05


#: Number of the model's parameters ``θ = (vx, vy, ax, ay, ε, λ)``.
PARAMETERS = 6
#: Indices of the creep amplitude's relative error ``ε`` and of ``λ = δ ln τ_c`` in ``θ``.
EPS, LAM = 4, 5
#: Rows' Jacobians kept at most (then forgotten at once and made again as asked for).
JACOBIANS_KEPT = 8192
#: Prior standard deviation of a jump of the drift after the full scan (``J``), nm.
JUMP_PRIOR_STD = 1000.0
#: A jump is taken into the model when its Wald statistic ``Jᵀ C_J⁻¹ J`` (χ² with 2
#: degrees of freedom were there none) passes this: 1 in 10⁸ by chance.
JUMP_GATE = 36.8
#: References that must follow a jump found while they were scanned again (one at the
#: scan's end, or one in the scan, needs two): with two, picking the best of the splits of
#: four references found a "jump" of 36 ± 7 nm in a run without one (rods seed 10,
#: statistic 23.7).
JUMP_CARRIERS = 3


class ScanDrift:
    """``θ = (vx, vy, ax, ay, ε, λ)`` (nm/s, nm/s², 1, 1) with its covariance, and the moves
    made before the full scan ended (``moves``: rows of ``(t, sx, sy)``, instrument s and
    nm). Times ``τ`` are s after the epoch ``epoch``. ``tau_std``: the prior σ of ``λ``."""

    def __init__(self, epoch: float, velocity_std: float, creep_amplitude: float, creep_tau: float,
                 acceleration_std: float = ACCELERATION_STD, creep_std: float = 0.0, tau_std: float = 0.0):
        self.epoch = float(epoch)
        self.theta = np.zeros(PARAMETERS)
        rel = creep_std / creep_amplitude if creep_amplitude > 0 else 0.0
        self.cov = np.diag([velocity_std ** 2] * 2 + [acceleration_std ** 2] * 2 + [max(rel, 1e-9) ** 2]
                           + [max(tau_std, 1e-9) ** 2])
        self.creep = (float(creep_amplitude), float(creep_tau))
        self._jacobians: dict[float, np.ndarray] = {}   # by τ, while the moves stand
        self.moves = np.zeros((0, 3))
        self.ended = False                   # the full scan has ended
        self.rows: dict = {}                 # each reference's components (h, z, var), by key
        self._prior = self.cov.copy()
        # the same with a jump ``J`` (2, nm) of the drift after the full scan's end, before
        # (or while) the references are scanned again: ``θ`` then ``J``, taken into the model
        # once it is evident, counting from ``tau_jump`` on
        self.tau_end: float | None = None    # the full scan's end, s after the epoch
        self.tau_jump: float | None = None   # the jump counts from here (s after the epoch)
        self._seen: dict = {}                # each keyed component's (n, τ0, τ1), by key
        self.info_j = np.zeros((PARAMETERS + 2, PARAMETERS + 2))
        self.eta_j = np.zeros(PARAMETERS + 2)
        self._prior_j = np.zeros((PARAMETERS + 2, PARAMETERS + 2))
        self._prior_j[:PARAMETERS, :PARAMETERS] = self._prior
        self._prior_j[PARAMETERS:, PARAMETERS:] = np.eye(2) * JUMP_PRIOR_STD ** 2
        self.stepped = False                 # the jump is in the model
        self.cov_j = self._prior_j.copy()    # the posterior with ``J`` (when stepped)
        self.jump = np.zeros(2)

    @staticmethod
    def thermal_jacobian(tau: float) -> np.ndarray:
        """``∂D(τ)/∂θ`` of the thermal part alone (``ε``'s and ``λ``'s columns zero), (2, 6)."""
        return np.hstack([np.eye(2) * tau, np.eye(2) * 0.5 * tau * tau, np.zeros((2, 2))])

    @staticmethod
    def velocity_jacobian(tau: float) -> np.ndarray:
        """``∂v(τ)/∂θ``: the thermal drift velocity at ``τ``, (2, 6)."""
        return np.hstack([np.eye(2), np.eye(2) * tau, np.zeros((2, 2))])

    @property
    def moves(self) -> np.ndarray:
        """The moves made before the full scan ended, rows of ``(t, sx, sy)``."""
        return self._moves

    @moves.setter
    def moves(self, value) -> None:
        self._moves = np.asarray(value, float).reshape(-1, 3)
        self._jacobians.clear()

    def _jacobian(self, tau: float) -> np.ndarray:
        """``∂D(τ)/∂θ``, kept by ``τ`` while the moves stand (read-only): every position
        taken from the full scan is put back by its row's, hundreds of thousands of times
        in a 1000-object run, at a thousand distinct rows."""
        key = float(tau)
        J = self._jacobians.get(key)
        if J is None:
            if len(self._jacobians) >= JACOBIANS_KEPT:
                self._jacobians.clear()
            a, tc = self.creep
            t, m = self.epoch + key, self._moves
            J = self.thermal_jacobian(key)
            J[:, EPS] = creep_offset(t, m[:, 0], m[:, 1:], a, tc)
            J[:, LAM] = creep_tau_sensitivity(t, m[:, 0], m[:, 1:], a, tc)
            J.flags.writeable = False
            self._jacobians[key] = J
        return J

    def jacobian(self, tau: float) -> np.ndarray:
        """``∂D(τ)/∂θ``, (2, 6): ``ε``'s column is the nominal creep of the scan's moves,
        ``λ``'s their creep per unit ``δ ln τ_c``."""
        return self._jacobian(tau).copy()

    @property
    def known(self) -> bool:
        """Whether the velocity is known in every direction (:data:`KNOWN_VELOCITY_STD`)."""
        return float(np.linalg.eigvalsh(self.cov[:2, :2])[-1]) < KNOWN_VELOCITY_STD ** 2

    def creep_at(self, tau: float) -> np.ndarray:
        """The creep (nm) of the moves made before the full scan ended, at ``τ``."""
        return self._jacobian(tau)[:, EPS].copy()

    def offset(self, tau: float) -> np.ndarray:
        """``D(τ)``, nm: the drift the full scan's row of time ``τ`` carried (after the scan,
        the jump since, if one is in the model)."""
        return self.jacobian(tau) @ self.theta + self.creep_at(tau) + self.step(tau)

    def step(self, tau: float) -> np.ndarray:
        """The jump in the model at ``τ`` (nm): ``J`` after the full scan's end, else 0."""
        return self.jump.copy() if self._after(tau) else np.zeros(2)

    def _after(self, tau: float) -> bool:
        return self.stepped and self.tau_jump is not None and tau >= self.tau_jump

    def _with_step(self, jac: np.ndarray, tau: float) -> np.ndarray:
        """``∂D(τ)/∂(θ, J)``, (2, 8), from ``jac = ∂D(τ)/∂θ``."""
        return np.hstack([jac, np.eye(2) if self._after(tau) else np.zeros((2, 2))])

    def offset_cov(self, tau: float) -> np.ndarray:
        """Covariance (nm²) of :meth:`offset`."""
        J = self.jacobian(tau)
        if self.stepped:
            J = self._with_step(J, tau)
            return J @ self.cov_j @ J.T
        return J @ self.cov @ J.T

    def projected_cov(self, normals, taus) -> np.ndarray:
        """Covariance (nm²) of the components ``n_k · D(τ_k)``, (m, m)."""
        H = np.array([np.asarray(n, float) @ self.jacobian(tau) for n, tau in zip(normals, taus)])
        return H @ self.cov @ H.T

    def between_cov(self, tau1: float, tau0: float) -> np.ndarray:
        """Covariance (nm²) of the drift from ``τ0`` to ``τ1`` as this model predicts it."""
        if self.stepped:
            J = self._with_step(self.jacobian(tau1), tau1) - self._with_step(self.jacobian(tau0), tau0)
            return J @ self.cov_j @ J.T
        J = self.jacobian(tau1) - self.jacobian(tau0)
        return J @ self.cov @ J.T

    def velocity_at(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """The velocity (nm/s) at ``τ`` and its covariance."""
        J = self.velocity_jacobian(tau)
        return J @ self.theta, J @ self.cov @ J.T

    def scan_ended(self, moves, tau: float | None = None) -> None:
        """The full scan has ended (at ``tau``, s after the epoch, if known: a jump of the
        drift after it can then be told); ``moves``: the scanner moves so far, ``(t, step)``."""
        self.moves = np.array([[t, s[0], s[1]] for t, s in moves], float)
        self.ended = True
        self.tau_end = self.tau_jump = None if tau is None else float(tau)

    def measure(self, n, z: float, tau1: float, tau0: float, var: float, creep1=None, lam1=None,
                key=None) -> None:
        """A reference seen at ``τ0`` in the full scan and at ``τ1`` again: ``z`` (nm, the
        nominal creep taken out) is the component along unit ``n`` of ``D(τ1) − D(τ0)``,
        with variance ``var`` (nm²). ``creep1``: the nominal creep (nm) at ``τ1`` of every
        move made so far, ``lam1`` its derivative by ``ln τ_c``
        (:func:`~nanoasm.drift.creep.creep_tau_sensitivity`);
        by default the scan's moves alone. ``key``: the reference it belongs to, kept so
        that a reference the others contradict can be taken out (:meth:`worst`,
        :meth:`remove`)."""
        J1 = self.jacobian(tau1)
        if creep1 is not None:
            J1[:, EPS] = np.asarray(creep1, float)
        if lam1 is not None:
            J1[:, LAM] = np.asarray(lam1, float)
        h = np.asarray(n, float) @ (J1 - self.jacobian(tau0))
        jumped = self.tau_jump is not None and tau0 < self.tau_jump <= tau1
        h = np.concatenate([h, np.asarray(n, float) if jumped else np.zeros(2)])
        if key is not None:
            self.rows.setdefault(key, []).append((h, float(z), float(var)))
            self._seen.setdefault(key, []).append((np.asarray(n, float), float(tau0), float(tau1)))
        self._add(h, float(z), float(var), 1.0)

    def _add(self, h: np.ndarray, z: float, var: float, sign: float) -> None:
        """Add (``sign`` 1) or take out (-1) one component, ``h`` over ``(θ, J)``."""
        self.info_j += sign * np.outer(h, h) / var
        self.eta_j += sign * h * z / var
        self._solve()

    @property
    def info(self) -> np.ndarray:
        """What the references measured of ``θ`` (a model without the jump)."""
        return self.info_j[:PARAMETERS, :PARAMETERS]

    @property
    def eta(self) -> np.ndarray:
        return self.eta_j[:PARAMETERS]

    def _solve(self) -> None:
        if self.stepped:
            cov = np.linalg.inv(np.linalg.inv(self._prior_j) + self.info_j)
            self.cov_j = 0.5 * (cov + cov.T)
            x = self.cov_j @ self.eta_j
            self.theta, self.jump = x[:PARAMETERS], x[PARAMETERS:]
            self.cov = self.cov_j[:PARAMETERS, :PARAMETERS].copy()
            return
        cov = np.linalg.inv(np.linalg.inv(self._prior) + self.info)
        self.cov = 0.5 * (cov + cov.T)
        self.theta = self.cov @ self.eta

    def _split(self, since: float):
        """The keyed components with the jump counted from ``since`` (s after the epoch):
        ``(rows by key, info, eta)`` over ``(θ, J)``; the unkeyed ones as measured."""
        rows, info, eta = {}, self.info_j.copy(), self.eta_j.copy()
        for key, comps in self.rows.items():
            out = []
            for (h, z, var), (n, tau0, tau1) in zip(comps, self._seen[key]):
                g = h.copy()
                g[PARAMETERS:] = n if tau0 < since <= tau1 else 0.0
                info += (np.outer(g, g) - np.outer(h, h)) / var
                eta += (g - h) * z / var
                out.append((g, z, var))
            rows[key] = out
        return rows, info, eta

    def mapped(self, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M θ, M cov Mᵀ)`` for a state whose first two rows are an offset after the full
        scan: with the jump in the model, it is added there (and its covariance)."""
        if not self.stepped:
            return M @ self.theta, M @ self.cov @ M.T
        step = np.zeros((M.shape[0], 2))
        step[:2] = np.eye(2)
        M = np.hstack([M, step])
        return M @ np.concatenate([self.theta, self.jump]), M @ self.cov_j @ M.T

    def jump_evidence(self, tears_only: bool = False) -> tuple[np.ndarray, np.ndarray, float, float]:
        """``(J, C_J, Jᵀ C_J⁻¹ J, since)``: the jump of the drift after the full scan began
        that the references measure, whichever of its times (``tears_only``: within the
        scan) fits them best, its covariance, Wald statistic and time (s after the epoch):
        :func:`.scan_jump.evidence`."""
        from .scan_jump import evidence

        return evidence(self, tears_only)

    def take_jump(self, since: float | None = None) -> None:
        """Take the jump into the model from now on, counting from ``since`` (s after the
        epoch; the full scan's end by default) (:meth:`jump_evidence`)."""
        if since is not None:
            self.rows, self.info_j, self.eta_j = self._split(since)
            self.tau_jump = float(since)
        self.stepped = True
        self._solve()

    def drop_jump(self) -> None:
        """Take the jump out of the model again (counted from the scan's end if taken again)."""
        if self.stepped and self.tau_end is not None:
            self.rows, self.info_j, self.eta_j = self._split(self.tau_end)
            self.tau_jump = self.tau_end
        self.stepped = False
        self.jump = np.zeros(2)
        self._solve()

    def disagreement(self, key) -> float:
        """χ² of reference ``key``'s components against ``θ`` measured by every other
        reference (and the prior): large when it is not what the others say, a neighbour
        taken for it, say; 0 for an unknown key."""
        rows = self.rows.get(key)
        if not rows:
            return 0.0
        k = PARAMETERS + 2 if self.stepped else PARAMETERS
        H = np.array([h[:k] for h, _, _ in rows])
        z = np.array([v for _, v, _ in rows])
        R = np.diag([var for _, _, var in rows])
        info = self.info_j[:k, :k] - H.T @ np.linalg.solve(R, H)
        eta = self.eta_j[:k] - H.T @ np.linalg.solve(R, z)
        cov = np.linalg.inv(np.linalg.inv(self._prior_j[:k, :k]) + info)
        r = z - H @ (cov @ eta)
        S = H @ cov @ H.T + R
        return float(r @ np.linalg.solve(0.5 * (S + S.T), r))

    def worst(self):
        """``(key, χ², components)`` of the reference the others contradict most, None
        without references kept by key."""
        if not self.rows:
            return None
        key = max(self.rows, key=lambda k: (self.disagreement(k), str(k)))
        return key, self.disagreement(key), len(self.rows[key])

    def remove(self, key) -> tuple[list, list]:
        """Take reference ``key``'s components out of the model; returns them (its rows
        and their times) for :meth:`restore`."""
        rows = self.rows.pop(key, [])
        for h, z, var in rows:
            self._add(h, z, var, -1.0)
        return rows, self._seen.pop(key, [])

    def restore(self, key, rows: list, seen: list) -> None:
        """Put reference ``key``'s components back as :meth:`remove` returned them (the
        jump counted from where it counts now)."""
        self.rows[key], self._seen[key] = list(rows), list(seen)
        for h, z, var in rows:
            self._add(h, z, var, 1.0)
        if self.tau_jump is not None:
            self.rows, self.info_j, self.eta_j = self._split(self.tau_jump)
            self._solve()

    def trial(self) -> ScanDrift:
        """A copy to try leaving references out on (:meth:`remove`, :meth:`take_jump`)
        without touching this one: its own references and sums, the moves' Jacobians
        shared (they do not change with the references)."""
        out = copy.copy(self)
        out.rows = {k: list(v) for k, v in self.rows.items()}
        out._seen = {k: list(v) for k, v in self._seen.items()}
        for name in ("info_j", "eta_j", "theta", "cov", "cov_j", "jump"):
            setattr(out, name, getattr(self, name).copy())
        return out

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "theta": self.theta.tolist(), "cov": self.cov.tolist(),
                "creep": list(self.creep), "moves": self.moves.tolist(), "prior": self._prior.tolist(),
                "ended": self.ended, "tau_end": self.tau_end, "info_j": self.info_j.tolist(), "eta_j": self.eta_j.tolist(),
                "stepped": self.stepped, "tau_jump": self.tau_jump}

    @classmethod
    def from_state(cls, state: dict) -> ScanDrift:
        out = cls(state["epoch"], 1.0, *state["creep"])
        out.theta = np.asarray(state["theta"], float)
        out.cov = np.asarray(state["cov"], float)
        if out.theta.size < PARAMETERS:          # a checkpoint from before ε: ε taken as 0, known
            grow = PARAMETERS - out.theta.size

            def pad(a):
                a = np.pad(np.asarray(a, float), (0, grow))
                a[-grow:, -grow:] += np.eye(grow) * 1e-18
                return a.tolist()

            out.theta, out.cov = np.append(out.theta, np.zeros(grow)), np.asarray(pad(out.cov))
            state = {**state, "prior": pad(state["prior"]), "info": pad(state["info"]),
                     "eta": np.append(np.asarray(state["eta"], float), np.zeros(grow)).tolist()}
        out.moves = np.asarray(state["moves"], float).reshape(-1, 3)
        out._prior = np.asarray(state["prior"], float)
        out._prior_j[:PARAMETERS, :PARAMETERS] = out._prior
        if "info_j" in state:                    # else a checkpoint from before the jump: none
            out.info_j, out.eta_j = np.asarray(state["info_j"], float), np.asarray(state["eta_j"], float)
            out.tau_end, out.stepped, out.tau_jump = state["tau_end"], bool(state["stepped"]), state["tau_jump"]
        else:
            out.info_j[:PARAMETERS, :PARAMETERS] = np.asarray(state["info"], float)
            out.eta_j[:PARAMETERS] = np.asarray(state["eta"], float)
        out.ended = bool(state["ended"])
        if out.stepped:
            out._solve()
        return out


def filter_theta(f, thermal: int, amplitude: float) -> tuple[np.ndarray, np.ndarray]:
    """``θ`` and its covariance as a drift filter ``f`` holds them once bootstrapped: its
    first ``thermal`` statics, the learnt creep amplitude error ``c ε`` (last) per the
    nominal ``amplitude``, and ``λ`` (0 in a filter from before it)."""
    old = f.tau_static is None          # a checkpoint from before λ: λ = 0
    idx = [*range(4, 4 + thermal), -1, -1 if old else 4 + f.tau_static]
    scale = np.ones(len(idx))            # θ's thermal part, c ε, λ
    scale[EPS], scale[LAM] = 1.0 / amplitude, 0.0 if old else 1.0
    P = f.P
    return f.x[idx] * scale, P[np.ix_(idx, idx)] * np.outer(scale, scale)
