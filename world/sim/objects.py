"""The truth of a simulated sample: each object's kind and its own physical constants.

The truth is not the planner's model, so dry-runs test robustness: every object gets, once, from a
seeded generator, its own object–substrate friction μos and shear coefficient ν
(relative spread ``[friction] scatter``), its own adhesion (``[adhesion] scatter``), a
pivot offset along its axis (``[push] pivot_scatter`` of its length, rods) and a
direction error of its motion (``[push] path_scatter``, particles). Objects with
15 ≤ σ ≤ 25 (seed §4.3.1: uncertain) get ``[sim] uncertain_gain`` times the spread of
pivot and path. Spreads are log-normal for the positive constants (relative standard
deviation exactly the ``scatter`` value, never negative) and normal for the offsets.

Adhesions (seed §4.2.1, scaled by contact area): a particle's F^a_ot and F^a_os follow
from the tip–substrate adhesion F^a_ts by JKR contact areas
(:func:`~nanoasm.world.particle_push.particle_adhesions`); a rod's or wire's F^a_os is
``[adhesion] object_ratio`` × F^a_ts (the seed's Fig. 4.14 assumes 20), its F^a_ot that
of a sphere of the rod's radius. Forces in nN, lengths in nm, angles in degrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from nanoasm.bodies import Body
from nanoasm.world.params import WorldParams
from nanoasm.world.particle_push import particle_adhesions
from nanoasm.world.pivot import Regime, aspect_regime

from .wire import initial_nodes, segment_bodies, segment_count



class Kind(IntEnum):
    """How the simulation moves an object."""

    PARTICLE = 0  # translates (seed §4.2)
    ROD = 1       # turns about the pivot of eq. 4.10 (σ ≤ 25)
    WIRE = 2      # bends (σ > 25)


def object_kind(body: Body) -> Kind:
    """The motion model of a scene object (its regime from σ = L/d for rods)."""
    if not body.elongated:
        return Kind.PARTICLE
    return Kind.WIRE if aspect_regime(body.length, body.diameter) is Regime.FLEXIBLE else Kind.ROD


@dataclass(frozen=True, eq=False)
class ObjectTable:
    """Per-object constants, arrays of shape ``(n,)`` indexed like the scene's objects.

    ``first_unit[i]``..``first_unit[i] + n_units[i]`` are object ``i``'s footprints in the
    contact space (one for a particle or rod, one per segment for a wire).
    """

    bodies: tuple[Body, ...]
    kind: np.ndarray
    mu_os: np.ndarray
    nu: np.ndarray
    f_os_a: np.ndarray
    f_ot_a: np.ndarray
    pivot_offset: np.ndarray   # fraction of the length, along the axis
    path_error: np.ndarray     # degrees, counter-clockwise
    first_unit: np.ndarray
    n_units: np.ndarray

    def __len__(self) -> int:
        return len(self.bodies)


def _lognormal(rng: np.random.Generator, rel_sd: float, n: int) -> np.ndarray:
    """Positive factors of mean 1 and relative standard deviation ``rel_sd``."""
    if rel_sd == 0:
        return np.ones(n)
    s = math.sqrt(math.log1p(rel_sd * rel_sd))
    return np.exp(s * rng.standard_normal(n) - 0.5 * s * s)


def build_objects(bodies: Sequence[Body], params: WorldParams, rng: np.random.Generator
                  ) -> tuple[ObjectTable, list[Body], list[int], dict[int, np.ndarray]]:
    """Draw the per-object truth and lay out the contact units.

    Returns ``(table, units, groups, wires)``: the table, the footprints in unit order,
    the object of each unit, and the initial nodes of each wire (by object index).
    Every draw is vectorised over the objects, in a fixed order.
    """
    n = len(bodies)
    kinds = np.array([object_kind(b) for b in bodies], dtype=np.int64)
    radius = np.array([b.radius for b in bodies], float)
    f_ts = params.adhesion.tip_substrate
    rt = params.tip.radius
    f_ot, f_os = particle_adhesions(f_ts, rt, radius)
    f_os = np.where(kinds == Kind.PARTICLE, f_os, params.adhesion.object_ratio * f_ts)

    fr = params.friction
    mu = fr.mu_os * _lognormal(rng, fr.scatter, n)
    nu = fr.nu * _lognormal(rng, fr.scatter, n)
    adh = _lognormal(rng, params.adhesion.scatter, n)
    gain = np.array([params.sim.uncertain_gain if b.elongated and b.length / b.diameter >= 15.0 else 1.0
                     for b in bodies])
    pivot = params.push.pivot_scatter * gain * rng.standard_normal(n)
    path = params.push.path_scatter * gain * rng.standard_normal(n)
    pivot = np.where(kinds == Kind.ROD, pivot, 0.0)
    path = np.where(kinds == Kind.PARTICLE, path, 0.0)

    units: list[Body] = []
    groups: list[int] = []
    wires: dict[int, np.ndarray] = {}
    first = np.zeros(n, np.int64)
    count = np.ones(n, np.int64)
    for i, b in enumerate(bodies):
        first[i] = len(units)
        if kinds[i] == Kind.WIRE:
            nodes = initial_nodes(b, segment_count(b.length, b.diameter))
            wires[i] = nodes
            segs = segment_bodies(b.id, nodes, b.diameter)
            units += segs
            count[i] = len(segs)
        else:
            units.append(b)
        groups += [i] * int(count[i])
    table = ObjectTable(tuple(bodies), kinds, mu, nu, f_os * adh, f_ot * adh, pivot, path, first, count)
    return table, units, groups, wires
