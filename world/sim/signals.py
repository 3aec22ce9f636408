"""From the forces on the tip to the photodiode signals the simulated AFM reports.

Forces (nN, AFM frame) on the tip: the lever's normal load ``k × deflection`` (the tip
pressed ``-z`` into a hard surface, plus any height it rides over an object) and a
lateral force: tip–substrate friction μts(F_z + F^a_ts) against the tip's motion, or
while it pushes (eq. 4.4) the object's contact force along the tip–object contact normal
plus the friction on the excess load against the motion, so an object pushed off-centre
twists the lever to its side (:mod:`~nanoasm.world.sim.push`). They reach the detector as
the seed describes (ch. 3):

- the cantilever frame by R(ψ) (eq. 3.7), then S̄_n, S̄_l by
  :func:`~nanoasm.world.cantilever.signals_from_force` (eq. 3.5, 3.6, 3.9, saturating);
- spurious signals by :func:`~nanoasm.world.cantilever.raw_signals` (eq. 3.28 inverted):
  normal-to-lateral cross-talk α, the substrate-reflection baseline A (``reflection_n``
  near the surface, fading with height over ``[sim] reflection_decay``) and the piezo-bow
  baseline B (rising linearly from 0 to ``reflection_l`` across the working area, the
  tilted free-scan line of the seed's Fig. 3.14), plus detector noise;
- the deflected tip sits at ``piezo + R(ψ)⁻¹ (C2 S̄_n, C1 S̄_l)`` (eq. 3.30-3.34,
  :func:`~nanoasm.world.cantilever.tip_offset`), which the executor compensates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.world.cantilever import (
    Cantilever,
    raw_signals,
    scan_rotation,
    signals_from_force,
    to_cantilever,
)
from nanoasm.world.params import WorldParams



def lever_from_params(params: WorldParams) -> Cantilever:
    """The :class:`Cantilever` of a world's ``[cantilever]`` table."""
    c = params.cantilever
    return Cantilever(spring_constant=c.k, normal_gain=c.K_n, lateral_gain=c.lateral_gain,
                      tip_height=c.tip_height, lever_length=c.length, c2=c.C2, c1_override=c.C1,
                      crosstalk=c.alpha, full_scale=c.signal_limit)


@dataclass(frozen=True, eq=False)
class SignalModel:
    """Lever, scan angle and detector of one simulated instrument."""

    lever: Cantilever
    psi: float
    reflection_n: float
    reflection_l: float
    noise_rms: float
    x0: float
    width: float
    reflection_decay: float = 1000.0

    @classmethod
    def from_params(cls, params: WorldParams, x0: float, width: float) -> SignalModel:
        c = params.cantilever
        return cls(lever_from_params(params), params.scanner.scan_angle, c.reflection_n,
                   c.reflection_l, c.signal_rms, float(x0), float(width), params.sim.reflection_decay)

    @property
    def offset_matrix(self) -> np.ndarray:
        """``M`` (2, 2) with tip offset ``M @ (S̄_n, S̄_l)`` nm in the AFM frame (eq. 3.30-3.34)."""
        rinv = scan_rotation(self.psi).T[:2, :2]
        return rinv @ np.diag([self.lever.c2, self.lever.c1])

    def tip_offset(self, sn_bar: np.ndarray, sl_bar: np.ndarray) -> np.ndarray:
        """``(n, 2)`` nm: where the deflected tip sits relative to the piezo."""
        return np.stack([sn_bar, sl_bar], axis=-1) @ self.offset_matrix.T

    def bar_signals(self, force: np.ndarray, deflection: np.ndarray):
        """Compensated signals ``(S̄_n, S̄_l)`` (V) for lateral forces ``force`` on the tip
        (nN, ``(n, 2)``, AFM frame) and deflections (nm)."""
        f = np.column_stack([force[:, 0], force[:, 1], self.lever.spring_constant * deflection])
        return signals_from_force(to_cantilever(f, self.psi), self.lever)

    def baselines(self, x: np.ndarray, height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(A, B)`` in V at scanner positions ``x`` with the tip ``height`` nm above the substrate."""
        a = self.reflection_n * np.exp(-np.maximum(height, 0.0) / self.reflection_decay)
        b = self.reflection_l * np.clip((x - self.x0) / self.width, 0.0, 1.0)
        return a, np.broadcast_to(b, np.shape(a))

    def raw(self, sn_bar: np.ndarray, sl_bar: np.ndarray, x: np.ndarray, height: np.ndarray,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Detector signals ``(S_n, S_l)`` in V: baselines, cross-talk, noise, saturation.

        ``x`` is the scanner x (nm) and ``height`` the tip's height above the substrate (nm).
        """
        a, b = self.baselines(x, height)
        s_n, s_l = raw_signals(sn_bar, sl_bar, x, x, 0.0, 0.0, 1.0, self.lever.crosstalk)
        s_n, s_l = s_n + a, s_l + b
        if self.noise_rms > 0:
            s_n = s_n + rng.normal(0.0, self.noise_rms, s_n.shape)
            s_l = s_l + rng.normal(0.0, self.noise_rms, s_l.shape)
        lim = self.lever.full_scale
        return np.clip(s_n, -lim, lim), np.clip(s_l, -lim, lim)


def twist_deg(sl_bar: float, lever: Cantilever) -> float:
    """|θx| in degrees for a compensated lateral signal (eq. 3.3, K_l ≈ K_n / l)."""
    return abs(math.degrees(lever.twist_gain * sl_bar))
