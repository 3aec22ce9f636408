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

Creep: each recorded move of the scanner by a step ``s`` (at least ``min_step`` long)
adds ``γ s log10(1 + (t - t_s) / τ)`` for ``t > t_s``: the piezo keeps extending along
the step, logarithmically (seed 3.7 refers creep to its ref. [50]).

Sign convention: a sample point at scene position ``p`` lies under the scanner-frame
position ``p + offset(t)``, with ``offset = thermal - creep`` (creep carries the tip
further along the step, so the sample appears to move back).
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.world.params import CreepParams, DriftParams

_BLOCK = 4096  # grid steps per noise block


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
    """

    def __init__(self, drift: DriftParams, creep: CreepParams, rng: np.random.Generator, *,
                 epoch: float = 0.0, grid: float = 1.0):
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

    # -- thermal drift ----------------------------------------------------------------------
    def _elapsed(self, t) -> np.ndarray:
        tau = np.asarray(t, float) - self.epoch
        if not np.all(np.isfinite(tau)):
            raise ValueError("times must be finite")
        if np.any(tau < 0):
            raise ValueError(f"times must not precede the epoch {self.epoch:g} s")
        return tau

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
        return _split(walk + tau[..., None] * self._v)

    def velocity(self, t):
        """Thermal drift velocity ``(vx, vy)`` in nm/s at time(s) ``t``."""
        tau = self._elapsed(t)
        k, u = self._nodes(tau)
        h = self.grid
        d00, d10 = (6 * u**2 - 6 * u) / h, 3 * u**2 - 4 * u + 1
        d01, d11 = (-6 * u**2 + 6 * u) / h, 3 * u**2 - 2 * u
        walk = d00 * self._w[k] + d10 * self._u[k] + d01 * self._w[k + 1] + d11 * self._u[k + 1]
        return _split(walk + self._v)

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
        return True

    def creep(self, t):
        """Creep ``(dx, dy)`` in nm at time(s) ``t``: the sum over recorded moves."""
        tq = np.asarray(t, float)
        out = np.zeros(tq.shape + (2,))
        if self._moves_t:
            flat = tq.reshape(-1)
            acc = np.zeros((flat.size, 2))
            ts, ss = np.asarray(self._moves_t), np.asarray(self._moves_s)
            cp = self.creep_params
            for i in range(0, ts.size, 256):  # bounded memory for many moves
                dt = np.maximum(flat[:, None] - ts[None, i:i + 256], 0.0)
                acc += np.log10(1.0 + dt / cp.tau) @ ss[i:i + 256]
            out = cp.amplitude * acc.reshape(out.shape)
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
