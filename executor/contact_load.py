"""The normal force a push needs: the least one that keeps the tip down (seed eq. 4.7, 4.20).

A tip pressed with F_z below F̄z lifts and slips over the object it pushes (seed §4.2.1):

    F̄z = ρ (μos + ν) sin θ / (cos θ − ρ μos sin θ) · F^a_os − F^a_ts

with θ the tip's contact angle (its half opening angle; the lever's twist adds a fraction
of a degree), ρ = 1 for a particle and ρ(l) of eq. 4.13 for a rod pushed at l (eq. 4.20).
F^a_os grows with the contact: a particle's by its JKR area, (R / r_tip)^(4/3) F^a_ts
(:func:`~nanoasm.world.particle_push.particle_adhesions`), a rod's ``object_ratio`` F^a_ts
(the seed's Fig. 4.14 takes 20).

No object's own μos, ν and adhesion are known before it is pushed: they scatter from one
object to the next (the world draws them about the nominal values; a real sample does
the same). :class:`ContactModel` takes the nominal values of ``nanoasm.world.params`` and
their relative spreads, and :func:`needed_normal_force` gives F̄z at ``sigmas`` standard
deviations above the nominal one: ln F̄z's object part ``A F^a_os`` has the spread
``√(s_A² + s_adh²)`` with ``s_A`` from the friction's spread through ∂ln A/∂ln μos and
∂ln A/∂ln ν (first order, each log-normal). :func:`push_preload` turns it into the lever's
deflection (F_z = k · deflection), never below the instrument's preload and never above
:func:`preload_cap` (a share of its Z range and of the detector's full scale); an object the tip slipped over all the same is pushed
harder still by the course's factor (:class:`~.course.Course`).

Why: with the instrument's 100 nm preload on the seed's 0.12 N/m lever (12 nN) the tip
slipped over 90 nm particles whose F̄z the world had drawn at 14.5 and 11.5 nN (wide seed
2, allpushed seed 6: the first push of each, found by its after-scan and pushed again).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from nanoasm.bodies import Body
from nanoasm.instrument import InstrumentConfig
from nanoasm.world.cantilever import Cantilever
from nanoasm.world.params import AdhesionParams, FrictionParams, TipParams
from nanoasm.world.particle_push import min_normal_force, particle_adhesions
from nanoasm.world.pivot import rho

#: Largest preload deflection, as a share of the Z range (also the slip factor's cap).
PRELOAD_CAP = 0.45
#: ... and as a share of the detector's full scale (the push's own forces need the rest):
#: 0.8 x 10 V x 89 nm/V is 712 nm, 85 nN on the seed's lever. A rod pushed 0.2 L from its
#: end once asked for 10.9 V (the bowtie at seed 2), which the DAC path refuses.
SIGNAL_SHARE = 0.8


def preload_cap(config: InstrumentConfig, lever: Cantilever) -> float:
    """The largest preload deflection (nm) a push may use: :data:`PRELOAD_CAP` of the Z
    range and :data:`SIGNAL_SHARE` of the detector's full scale, whichever is less (never
    less than the instrument's own preload)."""
    detector = SIGNAL_SHARE * lever.full_scale * lever.normal_gain
    return max(config.preload, min(PRELOAD_CAP * config.z_range, detector))


@dataclass(frozen=True)
class ContactModel:
    """Nominal contact mechanics the executor assumes (seed §4.2.1, eq. 4.5-4.7): the tip's
    half opening angle (deg), the tip-substrate adhesion F^a_ts (nN), μos and ν, a rod's
    adhesion ratio F^a_os / F^a_ts, and the relative spreads of the friction and the
    adhesion from object to object."""

    half_angle: float = TipParams().half_angle
    tip_adhesion: float = AdhesionParams().tip_substrate
    mu_os: float = FrictionParams().mu_os
    nu: float = FrictionParams().nu
    object_ratio: float = AdhesionParams().object_ratio
    friction_spread: float = FrictionParams().scatter
    adhesion_spread: float = AdhesionParams().scatter

    def object_adhesion(self, body: Body, tip_radius: float) -> float:
        """Nominal F^a_os (nN) of ``body`` under a tip of ``tip_radius`` nm."""
        if body.kind == "particle":
            return float(particle_adhesions(self.tip_adhesion, tip_radius, body.radius)[1])
        return self.object_ratio * self.tip_adhesion

    def log_spread(self, r: float) -> float:
        """Standard deviation of ln(A F^a_os), A = ρ(μos + ν) sin θ / (cos θ − ρ μos sin θ)."""
        th = math.radians(self.half_angle)
        m = r * self.mu_os
        d_mu = self.mu_os / (self.mu_os + self.nu) + m * math.sin(th) / (math.cos(th) - m * math.sin(th))
        d_nu = self.nu / (self.mu_os + self.nu)
        s_f = math.sqrt(math.log1p(self.friction_spread ** 2))
        s_a = math.sqrt(math.log1p(self.adhesion_spread ** 2))
        return math.hypot(s_f * math.hypot(d_mu, d_nu), s_a)


def push_point(body: Body, tip) -> float:
    """Where along a rod (nm from its nearer end, within [0, L/2]) the tip at ``tip`` meets it."""
    a = math.radians(body.angle or 0.0)
    u = (tip[0] - body.at[0]) * math.cos(a) + (tip[1] - body.at[1]) * math.sin(a)
    return min(max(body.length / 2 - abs(u), 0.0), body.length / 2)


def needed_normal_force(body: Body, tip_radius: float, model: ContactModel, sigmas: float,
                        l: float | None = None) -> float:
    """F̄z (nN) of pushing ``body`` at ``sigmas`` standard deviations of the object-to-object
    spread above its nominal value; a rod at ``l`` nm from its nearer end (eq. 4.20)."""
    r = 1.0 if body.kind != "rod" or l is None else float(rho(l, body.length))
    f_os = model.object_adhesion(body, tip_radius)
    transmitted = float(min_normal_force(model.half_angle, model.mu_os, model.nu, f_os, 0.0, r))
    if not math.isfinite(transmitted):
        return math.inf
    return transmitted * math.exp(sigmas * model.log_spread(r)) - model.tip_adhesion


def push_preload(f_z: float, config: InstrumentConfig, lever: Cantilever) -> float:
    """The preload deflection (nm) that presses the tip with ``f_z`` nN on ``lever``, within
    [the instrument's preload, :func:`preload_cap`]."""
    want = f_z / lever.spring_constant if math.isfinite(f_z) else math.inf
    return min(max(config.preload, want), preload_cap(config, lever))
