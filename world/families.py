"""Generated scene families for sweeps and benchmarks: (scene, layout) pairs by seed.

Each family is a kind of sample and a layout its objects can fill:

==========  ========  ====================================  =================================
family      area, nm  objects                               slots
==========  ========  ====================================  =================================
tiny        1500      5 particles                           a particle dimer
sparse      4000      12 particles                          4 particles (a square)
dense       4000      70 particles                          6 particles (a hexagon)
rods        4000      4 rods, 10 particles                  a rod between two particles
mixed       5000      3 rods, 24 particles, 2 electrodes    a bowtie of 4 particles between
                                                            the electrodes, a rod below
==========  ========  ====================================  =================================

Particles are 80-100 nm and particle slots 90 nm, rods 500-700 nm long and 60-80 nm
thick and rod slots 600 x 70 nm, so every object fits every slot of its kind within the
default tolerance (25 % in size). The electrodes of ``mixed`` are obstacles in the scene
and keep-outs in the layout. No object starts within 100 nm of a slot, and every kind of
slot has at least one spare object that fits it (else the scene is drawn again from a
seed derived from the family's; the counts above are before the objects near slots
and electrodes are taken out). Drift: a steady velocity of ``drift`` nm/s in a direction
drawn from the seed, plus the world's default random walk. The same family, seed and
drift give the same pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.cad.layout import Keepout, Layout, Tolerance, layout_from_dict, size_ok

from .params import DriftParams
from .random_scene import SceneSpec, random_scene
from .scene import Obstacle, Scene, scene_from_dict

#: Least clearance between a slot and any object of the generated scene, nm.
SLOT_CLEARANCE = 100.0
PARTICLE_SLOT = 90.0
ROD_SLOT = (600.0, 70.0)          # length, diameter
#: Steady drift speed of a family unless given, nm/s.
DEFAULT_DRIFT = 0.3
#: Scenes drawn (from seeds derived from the family's) until one has a spare object for
#: every kind of slot.
ATTEMPTS = 20


@dataclass(frozen=True)
class Family:
    """One family: its side (nm), object counts, and whether it has electrodes."""

    name: str
    side: float
    particles: int
    rods: int = 0
    electrodes: bool = False

    def slots(self) -> tuple[Body, ...]:
        c = self.side / 2
        particle = lambda i, x, y: Body(f"s{i}", "particle", (x, y), PARTICLE_SLOT)  # noqa: E731
        if self.name == "tiny":
            return particle(1, c - 60, c), particle(2, c + 60, c)
        if self.name == "rods":
            reach = ROD_SLOT[0] / 2 + PARTICLE_SLOT / 2 + 40
            return (Body("bar", "rod", (c, c), ROD_SLOT[1], 0.0, ROD_SLOT[0]),
                    particle(1, c - reach, c), particle(2, c + reach, c))
        if self.name == "mixed":
            return (particle(1, c - 200, c - 100), particle(2, c - 200, c + 100),
                    particle(3, c + 200, c - 100), particle(4, c + 200, c + 100),
                    Body("bar", "rod", (c, c - 900), ROD_SLOT[1], 0.0, ROD_SLOT[0]))
        n = 4 if self.name == "sparse" else 6
        r = 150 / (2 * math.sin(math.pi / n))          # neighbours 150 nm apart
        return tuple(particle(i + 1, c + r * math.cos(2 * math.pi * i / n + math.pi / n),
                              c + r * math.sin(2 * math.pi * i / n + math.pi / n)) for i in range(n))

    def electrode_polygons(self) -> tuple[tuple[tuple[float, float], ...], ...]:
        if not self.electrodes:
            return ()
        c, s = self.side / 2, self.side
        left = ((0.0, c - 300), (c - 600, c - 300), (c - 600, c + 300), (0.0, c + 300))
        right = ((c + 600, c - 300), (s, c - 300), (s, c + 300), (c + 600, c + 300))
        return left, right


FAMILIES: dict[str, Family] = {f.name: f for f in (
    Family("tiny", 1500.0, 5),
    Family("sparse", 4000.0, 12),
    Family("dense", 4000.0, 70),
    Family("rods", 4000.0, 10, rods=4),
    Family("mixed", 5000.0, 24, rods=3, electrodes=True),
)}


def family(name: str) -> Family:
    """The family called ``name``; ValueError listing the names otherwise."""
    try:
        return FAMILIES[name]
    except KeyError:
        raise ValueError(f"unknown scene family {name!r}; one of {', '.join(FAMILIES)}") from None


def _spare(objects: tuple[Body, ...], slots: tuple[Body, ...]) -> bool:
    """More objects fit each kind of slot than there are such slots."""
    tol = Tolerance()
    return all(sum(size_ok(t, o, tol) for o in objects if o.kind == t.kind)
               > sum(u.kind == t.kind for u in slots) for t in slots)


def _clear_of(body: Body, others: tuple[Body, ...], clearance: float) -> bool:
    g = body.geometry()
    return all(shapely.distance(g, o.geometry()) >= body.radius + o.radius + clearance for o in others)


def family_case(name: str, seed: int, drift: float = DEFAULT_DRIFT) -> tuple[Scene, Layout]:
    """The scene and layout of family ``name`` for ``seed`` with ``drift`` nm/s of drift.

    Raises
    ------
    ValueError
        For an unknown family, a negative seed or a drift that is negative or not finite.
    """
    fam = family(name)
    if seed < 0:
        raise ValueError(f"seed must not be negative, got {seed}")
    if not (math.isfinite(drift) and drift >= 0):
        raise ValueError(f"drift must be finite and >= 0 nm/s, got {drift!r}")
    direction = np.random.default_rng([seed, 7]).uniform(0.0, 2.0 * math.pi)
    velocity = (round(drift * math.cos(direction), 6), round(drift * math.sin(direction), 6))
    spec = SceneSpec(area=(fam.side, fam.side), particles=fam.particles, rods=fam.rods,
                     particle_diameter=(80.0, 100.0), rod_length=(500.0, 700.0), rod_diameter=(60.0, 80.0),
                     drift=DriftParams(velocity, DriftParams().random_walk))
    slots = fam.slots()
    polygons = fam.electrode_polygons()
    pads = shapely.union_all([shapely.Polygon(q) for q in polygons]) if polygons else None
    for attempt in range(ATTEMPTS):
        base = random_scene(spec, seed + 1_000_003 * attempt)
        kept = tuple(o for o in base.objects if _clear_of(o, slots, SLOT_CLEARANCE) and (
            pads is None or shapely.distance(o.geometry(), pads) >= o.radius + spec.gap))
        if _spare(kept, slots):
            break
    else:  # pragma: no cover - the families leave plenty of room
        raise RuntimeError(f"family {name}: no feasible scene for seed {seed} in {ATTEMPTS} attempts")
    obstacles = tuple(Obstacle(q, 30.0) for q in polygons)
    scene = replace(base, objects=kept, obstacles=obstacles, seed=seed)
    scene = scene_from_dict(scene.to_dict(), f"family {name}")
    layout = Layout((fam.side, fam.side), slots, tuple(Keepout(q) for q in polygons), name=f"{name}-{seed}")
    return scene, layout_from_dict(layout.to_dict(), f"family {name}")
