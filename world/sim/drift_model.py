"""The true drift of scanner versus sample: thermal drift and piezo creep.

Thermal drift is a steady velocity plus a random walk: the drift velocity fluctuates
as white noise about its steady value, so the offset wanders about the steady drift as
a Wiener process of intensity ``q = random_walk`` (nm/√s, the unit of the scene's
``[drift] random_walk``): Var x(t) = q² t per axis. It is sampled exactly on a fixed
internal grid (step ``grid`` s) and interpolated between grid nodes by a smooth (C1
Hermite) step, so the tip never sees a jump. Grid block ``b`` draws its noise from its own stream
``SeedSequence(entropy, spawn_key=(b,))``, so the drift at any time is a deterministic
function of the model's seed alone: how the queries are chunked or ordered does not
matter. Times are stored relative to an ``epoch`` (the run's start).

Drift change (``[drift_change]``, off by default): the steady part of the thermal offset
is ``v t + a t²/2`` (``a`` the ``acceleration``: thermal settling), and jumps of
``jump`` nm (a knock, a thermal shock) start at ``jump_at`` s and, if ``jump_every > 0``,
every ``jump_every`` s after; each is a C1 smoothstep ``3p² - 2p³`` over ``jump_duration``
s, so the offset stays smooth (steps may overlap). Jump ``k``'s direction is uniform,
drawn from the stream ``SeedSequence(entropy, spawn_key=(k // 256, 1))``: apart from
the walk's, so jumps never change the walk's draws.

Creep: each recorded move of the scanner by a step ``s`` (at least ``min_step`` long)
adds ``γ s log10(1 + (t - t_s) / τ)`` for ``t > t_s``: the piezo keeps extending along
the step, logarithmically (seed 3.7 refers creep to its ref. [50]). No move is ever
forgotten; once there are thousands, the old ones are summed as one power series
(:mod:`.creep_sum`, exact to float rounding), so a query costs the same late in a long
run as early.

Sign convention: a sample point at scene position ``p`` lies under the scanner-frame
position ``p + offset(t)``, with ``offset = thermal - creep`` (creep carries the tip
further along the step, so the sample appears to move back).
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.world.params import CreepParams, DriftChangeParams, DriftParams

from .creep_sum import CreepSum

_BLOCK = 4096  # grid steps per noise block
_JUMP_BLOCK = 256  # jump directions per stream
_JUMP_STREAM = 1  # second spawn-key word of the jumps' streams (the walk's keys have one word)


class DriftModel:
    """Thermal drift and creep of one simulated instrument.

    Parameters
    ----------
    drift, creep : DriftParams, CreepParams
        ``[drift]`` and ``[creep]`` of the world (any object with the same attributes).
    rng : numpy.random.Generator
        Consumed once, at construction, for the model's own seed.
    epoch : float
        Instrument time (s) at which the drift is zero: the first full scan of the run.
    grid : float
        Step (s) of the internal grid of the random walk.
    change : DriftChangeParams, optional
        ``[drift_change]`` of the world: acceleration and jumps (default: none).
    """

    def __init__(self, drift: DriftParams, creep: CreepParams, rng: np.random.Generator, *,
                 epoch: float = 0.0, grid: float = 1.0, change: DriftChangeParams | None = None):
        if not (math.isfinite(grid) and grid > 0):
            raise ValueError(f"grid must be positive and finite, got {grid}")
        if not math.isfinite(epoch):
            raise ValueError(f"epoch must be finite, got {epoch}")
        self.drift = drift
        self.creep_params = creep
        self.epoch = float(epoch)
        self.grid = float(grid)
        self._entropy = [int(v) for v in rng.integers(0, 2**63, size=2)]
        self._v = np.asarray(drift.velocity, float)
        self._q = float(drift.random_walk)
        self._w = np.zeros((1, 2))  # random-walk position at grid nodes
        self._u = np.zeros((1, 2))  # random-walk velocity at grid nodes
        self._moves_t: list[float] = []
        self._moves_s: list[tuple[float, float]] = []
        self._sum = CreepSum(creep.tau)             # their creep, summed fast
        self.change = DriftChangeParams() if change is None else change
        self._a = np.asarray(self.change.acceleration, float)
        self._dirs = np.zeros((0, 2))  # unit direction of each jump
        self._sums = np.zeros((1, 2))  # _sums[k]: sum of the first k directions

    # -- thermal drift ----------------------------------------------------------------------
    def _elapsed(self, t) -> np.ndarray:
        tau = np.asarray(t, float) - self.epoch
        if not np.all(np.isfinite(tau)):
            raise ValueError("times must be finite")
        if np.any(tau < -1e-6):         # a microsecond before: the epoch itself, summed otherwise
            raise ValueError(f"times must not precede the epoch {self.epoch:g} s")
        return np.maximum(tau, 0.0)

    def _extend(self, nodes: int) -> None:
        """Generate grid nodes (block by block, each from its own stream) up to ``nodes``."""
        h = self.grid
        # (position, velocity) increment noise: a Wiener process on the position only
        chol = self._q * np.array([[h**0.5, 0.0], [0.0, 0.0]])
        while self._w.shape[0] <= nodes:
            b = (self._w.shape[0] - 1) // _BLOCK
            gen = np.random.default_rng(np.random.SeedSequence(self._entropy, spawn_key=(b,)))
            z = gen.standard_normal((_BLOCK, 2, 2))  # step, axis, (position, velocity) noise
            e = z @ chol.T  # e[..., 0]: position increment noise, e[..., 1]: velocity increment
            u = self._u[-1] + np.cumsum(e[:, :, 1], axis=0)
            u_prev = np.vstack([self._u[-1:], u[:-1]])
            w = self._w[-1] + np.cumsum(h * u_prev + e[:, :, 0], axis=0)
            self._w = np.vstack([self._w, w])
            self._u = np.vstack([self._u, u])

    def _nodes(self, tau: np.ndarray):
        s = tau / self.grid
        k = np.floor(s).astype(np.int64)
        self._extend(int(k.max(initial=0)) + 1)
        return k, (s - k)[..., None]

    def thermal(self, t):
        """Thermal drift ``(dx, dy)`` in nm at instrument time(s) ``t`` (scalar or array)."""
        tau = self._elapsed(t)
        k, u = self._nodes(tau)
        h = self.grid
        h00, h10 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u
        h01, h11 = -2 * u**3 + 3 * u**2, u**3 - u**2
        walk = (h00 * self._w[k] + h10 * h * self._u[k]
                + h01 * self._w[k + 1] + h11 * h * self._u[k + 1])
        out = walk + tau[..., None] * self._v
        if np.any(self._a):
            out = out + 0.5 * tau[..., None] ** 2 * self._a
        if self.change.jump > 0:
            out = out + self._jumps(tau)[0]
        return _split(out)

    def velocity(self, t):
        """Thermal drift velocity ``(vx, vy)`` in nm/s at time(s) ``t``."""
        tau = self._elapsed(t)
        k, u = self._nodes(tau)
        h = self.grid
        d00, d10 = (6 * u**2 - 6 * u) / h, 3 * u**2 - 4 * u + 1
        d01, d11 = (-6 * u**2 + 6 * u) / h, 3 * u**2 - 2 * u
        walk = d00 * self._w[k] + d10 * self._u[k] + d01 * self._w[k + 1] + d11 * self._u[k + 1]
        out = walk + self._v
        if np.any(self._a):
            out = out + tau[..., None] * self._a
        if self.change.jump > 0:
            out = out + self._jumps(tau)[1]
        return _split(out)

    # -- drift change: jumps ------------------------------------------------------------------
    def _extend_jumps(self, n: int) -> None:
        """Draw jump directions (stream by stream) until there are at least ``n``."""
        while self._dirs.shape[0] < n:
            b = self._dirs.shape[0] // _JUMP_BLOCK
            gen = np.random.default_rng(np.random.SeedSequence(self._entropy, spawn_key=(b, _JUMP_STREAM)))
            angle = gen.uniform(0.0, 2.0 * math.pi, _JUMP_BLOCK)
            dirs = np.column_stack([np.cos(angle), np.sin(angle)])
            self._dirs = np.vstack([self._dirs, dirs])
            self._sums = np.vstack([self._sums, self._sums[-1] + np.cumsum(dirs, axis=0)])

    def _jumps(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Offset and velocity ``(..., 2)`` of the jumps at elapsed times ``tau``.

        Jump ``k`` starts at ``jump_at + k jump_every`` (only ``k = 0`` when ``jump_every``
        is 0); those ended by ``tau`` add their whole step through the running sums of the
        directions, those in progress their smoothstep. The phase is clipped, so which
        side of a boundary a time is counted on changes nothing.
        """
        c = self.change
        rel = tau - c.jump_at
        if c.jump_every > 0:
            started = np.floor(np.maximum(rel, 0.0) / c.jump_every).astype(np.int64) + 1
            done = np.maximum(rel - c.jump_duration, -c.jump_every)
            ended = np.floor(done / c.jump_every).astype(np.int64) + 1
        else:
            started, ended = np.ones(rel.shape, np.int64), np.zeros(rel.shape, np.int64)
        self._extend_jumps(int(started.max(initial=1)))
        k = ended[..., None] + np.arange(int((started - ended).max(initial=1)))  # (..., m) in progress
        live = k < started[..., None]
        k = np.minimum(k, started[..., None] - 1)
        p = np.clip((rel[..., None] - k * c.jump_every) / c.jump_duration, 0.0, 1.0)
        step = np.where(live, p * p * (3.0 - 2.0 * p), 0.0)[..., None]
        rate = np.where(live, 6.0 * p * (1.0 - p) / c.jump_duration, 0.0)[..., None]
        dirs = self._dirs[k]
        return (c.jump * (self._sums[ended] + (step * dirs).sum(axis=-2)),
                c.jump * (rate * dirs).sum(axis=-2))

    # -- creep -------------------------------------------------------------------------------
    def record_move(self, t: float, dx: float, dy: float) -> bool:
        """Register a scanner move by ``(dx, dy)`` nm completed at time ``t``.

        Moves shorter than ``min_step`` are ignored (returns False). The simulated
        instrument records each completed XY move, so creep follows the moves made.
        """
        if not all(math.isfinite(v) for v in (t, dx, dy)):
            raise ValueError("move time and displacement must be finite")
        self._elapsed(t)
        if math.hypot(dx, dy) < self.creep_params.min_step or self.creep_params.amplitude == 0:
            return False
        self._moves_t.append(float(t))
        self._moves_s.append((float(dx), float(dy)))
        self._sum.add(float(t), (float(dx), float(dy)))
        return True

    @property
    def last_move(self) -> float:
        """Time (s) of the last recorded move (-inf before the first)."""
        return self._moves_t[-1] if self._moves_t else -math.inf

    def set_moves(self, times, steps) -> None:
        """Replace the recorded moves (a restored state): times (s) and steps (nm) in order."""
        self._moves_t = [float(v) for v in times]
        self._moves_s = [(float(a), float(b)) for a, b in steps]
        self._sum = CreepSum(self.creep_params.tau)
        for t, s in zip(self._moves_t, self._moves_s):
            self._sum.add(t, s)

    def creep(self, t):
        """Creep ``(dx, dy)`` in nm at time(s) ``t``: the sum over recorded moves, the
        old ones folded into a power series once there are many (:mod:`.creep_sum`)."""
        tq = np.asarray(t, float)
        out = np.zeros(tq.shape + (2,))
        if self._moves_t:
            out = self.creep_params.amplitude * self._sum(tq.reshape(-1)).reshape(out.shape)
        return _split(out)

    def offset(self, t):
        """Total offset ``(dx, dy)`` in nm: where the sample appears shifted in the scanner
        frame at time(s) ``t`` (``thermal - creep``)."""
        tx, ty = self.thermal(t)
        cx, cy = self.creep(t)
        return tx - cx, ty - cy


def _split(a: np.ndarray):
    """``(..., 2)`` array to a pair of arrays (floats for scalar queries)."""
    x, y = a[..., 0], a[..., 1]
    if x.ndim == 0:
        return float(x), float(y)
    return x, y
