"""Frame stages from a tip path to DAC codes: drift, scan angle, deflection, codes.

Each stage is a pure function over ``(n, ·)`` arrays. Frames (see
:mod:`nanoasm.instrument`): the *layout frame* is the frame of the run's first full
scan; a sample point at layout position ``p`` lies under the scanner-frame position
``p + d(t)`` (``d`` the drift offset); the *scanner frame* is the AFM frame of eq. 3.7 and
of the DAC (``full_scan`` and ``scan_line`` use it too, so positions are not rotated).
The scan angle ψ enters where the seed puts it: the lever's deflection ``δ`` (eq.
3.30-3.34, cantilever frame) reaches the AFM frame as ``R(ψ)⁻¹ δ`` (eq. 3.7, 3.12), and
the piezo is commanded to ``target - R(ψ)⁻¹ δ`` so that the deflected tip lands on the
target (§3.6.2). Only XY is compensated: the Z command ``-preload`` *is* the deflection
the push wants.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from nanoasm.errors import InstrumentLimitError
from nanoasm.instrument import AXES, InstrumentConfig
from nanoasm.param import number
from nanoasm.world.cantilever import SEED_LEVER, Cantilever, tip_offset

#: A drift offset: ``None`` (none), a constant ``(dx, dy)`` in nm, or a callable mapping
#: times ``(n,)`` s to offsets ``(n, 2)`` nm (vectorised; e.g. :class:`LinearDrift`).
DriftLike = None | tuple[float, float] | Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class LinearDrift:
    """Drift offset ``offset + velocity (t - t_ref)``: a drift filter's prediction.

    ``offset`` in nm at ``t_ref`` (instrument s), ``velocity`` in nm/s.
    """

    offset: tuple[float, float] = (0.0, 0.0)
    velocity: tuple[float, float] = (0.0, 0.0)
    t_ref: float = 0.0

    def __post_init__(self) -> None:
        for name in ("offset", "velocity"):
            v = tuple(getattr(self, name))
            if len(v) != 2:
                raise ValueError(f"{name} must be two numbers (x, y), got {v!r}")
            object.__setattr__(self, name, tuple(number(f"{name}[{i}]", c) for i, c in enumerate(v)))
        object.__setattr__(self, "t_ref", number("t_ref", self.t_ref))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Offsets ``(n, 2)`` nm at times ``t`` ``(n,)`` s."""
        dt = np.asarray(t, float).reshape(-1, 1) - self.t_ref
        return np.asarray(self.offset) + dt * np.asarray(self.velocity)

    @property
    def speed(self) -> float:
        return math.hypot(*self.velocity)


def as_drift(drift: DriftLike) -> Callable[[np.ndarray], np.ndarray]:
    """A vectorised drift callable from any :data:`DriftLike`; constants become
    :class:`LinearDrift` with zero velocity."""
    if drift is None:
        return LinearDrift()
    if callable(drift):
        return drift
    d = tuple(np.asarray(drift, float).ravel()) if np.ndim(drift) else ()
    if len(d) != 2:
        raise ValueError(f"drift must be None, (dx, dy) in nm or a callable of time, got {drift!r}")
    try:
        return LinearDrift(offset=d)
    except ValueError as err:
        raise ValueError(f"drift: {err}") from None


def drift_at(drift: Callable[[np.ndarray], np.ndarray], t: np.ndarray) -> np.ndarray:
    """Evaluate ``drift`` at times ``t`` ``(n,)``; ``(n, 2)`` nm, refusing non-finite values."""
    t = np.asarray(t, float)
    d = np.asarray(drift(t), float)
    if d.shape != (t.shape[0], 2):
        raise ValueError(f"drift must map {t.shape[0]} times to an ({t.shape[0]}, 2) array, "
                         f"got shape {d.shape}")
    bad = ~np.isfinite(d).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InstrumentLimitError(f"drift is not finite at t = {t[i]:.6g} s: {tuple(d[i])}; nothing sent")
    return d


@dataclass(frozen=True)
class PushLoad:
    """Expected mean compensated signals while pushing (V): ``S̄_n`` and ``S̄_l`` of eq. 3.28."""

    sn_bar: float
    sl_bar: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "sn_bar", number("sn_bar", self.sn_bar))
        object.__setattr__(self, "sl_bar", number("sl_bar", self.sl_bar))

    @classmethod
    def from_preload(cls, config: InstrumentConfig, lever: Cantilever = SEED_LEVER,
                     sl_bar: float = 0.0) -> PushLoad:
        """The preload's deflection signal ``S̄_n = preload / K_n`` (hard surface)."""
        return cls(config.preload / lever.normal_gain, sl_bar)


def deflection_offset(load: PushLoad, psi_deg: float, lever: Cantilever = SEED_LEVER) -> np.ndarray:
    """``(R(ψ)⁻¹ δ)_xy`` in nm, scanner frame: the deflected tip's offset from the piezo.

    ``δ = (C2 S̄_n, C1 S̄_l, K_n S̄_n)`` in the cantilever frame (eq. 3.30-3.34), rotated
    by ``R(ψ)⁻¹`` (eq. 3.7). Signals beyond the detector's ``full_scale`` are refused.
    """
    for name, v in (("sn_bar", load.sn_bar), ("sl_bar", load.sl_bar)):
        if abs(v) > lever.full_scale:
            raise ValueError(f"load.{name} = {v:g} V exceeds the detector's ±{lever.full_scale:g} V")
    return np.asarray(tip_offset(load.sn_bar, load.sl_bar, number("psi_deg", psi_deg), lever)[:2], float)


def to_scanner(xy: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Layout-frame points ``(n, 2)`` nm to the scanner frame: ``p + d`` with ``d`` ``(n, 2)`` or ``(2,)``."""
    return np.asarray(xy, float) + offset


def compensate(xy: np.ndarray, fraction: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Piezo commands ``(n, 2)`` nm that put the tip on scanner-frame targets ``xy``:
    ``xy - f R⁻¹δ`` with ``f`` ``(n,)`` the fraction of the push load held."""
    return np.asarray(xy, float) - np.asarray(fraction, float)[:, None] * np.asarray(offset, float)


def uncompensate(cmd: np.ndarray, fraction: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Where the deflected tip is for piezo commands ``cmd``: ``cmd + f R⁻¹δ`` (§3.6.2)."""
    return np.asarray(cmd, float) + np.asarray(fraction, float)[:, None] * np.asarray(offset, float)


def nm_to_codes(nm: np.ndarray, config: InstrumentConfig) -> np.ndarray:
    """Scanner-frame nm ``(n, 3)`` to the nearest DAC codes ``(n, 3)`` int64.

    Never clips: a non-finite value or one outside the scanner range raises
    :class:`~nanoasm.errors.InstrumentLimitError` naming the sample.
    """
    nm = np.asarray(nm, float)
    tol = 1e-9 * np.maximum(1.0, config.upper - config.lower)
    out = ~((nm >= config.lower - tol) & (nm <= config.upper + tol))
    if out.any():
        i, a = np.argwhere(out)[0]
        raise InstrumentLimitError(f"sample {i}: {AXES[a]} = {nm[i, a]:.6g} nm outside the scanner "
                                   f"range [{config.lower[a]:g}, {config.upper[a]:g}] nm; nothing sent")
    return config.nm_to_codes(nm)


def quantisation_error(config: InstrumentConfig) -> np.ndarray:
    """Worst-case rounding error of a position, nm: ``(xy, z)``, half a code per axis
    (XY as the Euclidean norm of both axes' halves)."""
    half = config.nm_per_code / 2
    return np.array([math.hypot(half[0], half[1]), half[2]])
