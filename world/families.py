"""Generated scene families for sweeps and benchmarks: (scene, layout) pairs by seed.

Each family is a kind of sample and a layout its objects can fill (slot geometry,
electrodes and the wire in :mod:`.family_slots`):

==========  ========  =====================================  ================================
family      area, nm  objects                                slots
==========  ========  =====================================  ================================
tiny        1500      5 particles                            a particle dimer
sparse      4000      12 particles                           4 particles (a square)
dense       4000      70 particles                           6 particles (a hexagon)
rods        4000      4 rods, 10 particles                   a rod between two particles
mixed       5000      3 rods, 24 particles, 2 electrodes     a bowtie of 4 particles between
                                                             the electrodes, a rod below
device      8000      exactly 12 particles, 2 rods, a wire,  a 1200 x 90 rod across the
                      2 electrodes (1400 nm gap)             gap, 4 particles above it and
                                                             4 below
allpushed   6000      exactly 9 particles, 2 electrodes      9 particles, a 3 x 3 grid of
                      (1600 nm gap)                          150 nm pitch in the gap
rodgap      10000     exactly 3 rods, 2 electrodes           3 parallel 1300 x 100 rods,
                      (2400 nm gap)                          400 nm apart, in the gap
wide        16000     20-60 particles (the count drawn from  12 particles, a 4 x 3 grid of
                      the seed), none within 2 µm of a slot  300 nm pitch in the centre
==========  ========  =====================================  ================================

``scaleN`` (:func:`scale_family`, N from 2 to 1000, not in :data:`FAMILIES`) is the scale
benchmark's: N particles at a constant density (1000 in 40 x 40 µm) and ``round(0.3 N)``
particle slots in a square grid spread over the area.

Particles are 80-100 nm and particle slots 90 nm, rods 500-700 nm long and 60-80 nm
thick and rod slots 600 x 70 nm (``device``: rods 1150-1300 x 80-100 nm; ``rodgap``:
1200-1400 x 90-110 nm), so every object fits every slot of its kind within the default
tolerance (25 % in size). The electrodes are obstacles (30 nm high) in the scene and
keep-outs in the layout, their gap centred in the area. The wire of ``device`` (2700 x 90
nm, L/d = 30: the simulator bends it, identification calls it a wire, an obstacle to
planning) lies above or below the electrodes, far from the slots: it is to be left
alone. No object starts within 100 nm of a slot (``wide``: 2 µm; its area is fixed at 16
µm and its particles spread uniformly over it, so the assignment of least total travel
pushes each 2-8 µm: 2.1-6.2 µm over seeds 1-60, median 3.5), and every kind of slot has
at least one spare object that fits it, but in ``allpushed`` and ``rodgap``, where
objects and slots are as many and every object must move (else the scene is drawn again
from a seed derived from the family's; the counts of the first five are before the
objects near slots and electrodes are taken out). In the last four every object also
keeps clear of the area's edge by the drift of a whole full scan (``border``: 450-1200
nm), so none that the layout needs is cut by the image border.

Drift: a steady velocity of ``drift`` nm/s in a direction drawn from the seed, plus the
world's default random walk; unless given, 0.3 nm/s for the first five families but
``dense`` (0.6 nm/s: a crowded scene at the fastest drift of the newer ones) and a speed
drawn from the seed in 0.15-0.6 nm/s for the last four.

The truth is not the executor's model: from the seed (its own generator, so the objects
do not depend on it) every family draws the creep amplitude and tau, each uniformly
within ±30 % (:data:`CREEP_SPREAD`) of the nominal 0.01 per decade and 0.1 s, and a
steady drift acceleration of magnitude uniform in 0 to 0.05/600 nm/s² (the drift velocity
changes by up to 0.05 nm/s in 10 min; :data:`MAX_ACCELERATION`) in a uniform direction.
They are the scene's ``[creep]`` and ``[drift_change]`` tables, so a written scene
reproduces them. The lever too is drawn from the seed (:func:`~.random_scene.draw_lever`:
``k``, ``K_n``, ``C1``, ``C2``, ``lateral_gain`` and ``alpha`` each within ±20 % of the seed's
lever), the scene's ``[cantilever]`` table: a dry-run calibrates it first and compensates
with what it measured. The same family, seed and drift give the same pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.cad.layout import Keepout, Layout, Tolerance, layout_from_dict, size_ok
from nanoasm.schema import Point

from . import family_slots as fs
from .family_slots import Slots
from .params import CreepParams, DriftChangeParams, DriftParams
from .random_scene import SceneSpec, draw_lever, random_scene
from .scene import Obstacle, Scene, scene_from_dict

#: Least clearance between a slot and any object of the generated scene, nm.
SLOT_CLEARANCE = 100.0
#: Steady drift speed of the first five families unless given (but ``dense``), nm/s.
DEFAULT_DRIFT = 0.3
#: Steady drift speed of ``dense`` unless given, nm/s.
DENSE_DRIFT = 0.6
#: Scenes drawn (from seeds derived from the family's) until one has the objects its
#: family asks for (see :class:`Family`).
ATTEMPTS = 20
#: Relative half-width of the uniform spread of creep amplitude and tau about nominal.
CREEP_SPREAD = 0.3
#: Largest drift acceleration drawn, nm/s²: the drift velocity changes by up to 0.05 nm/s
#: in 10 min.
MAX_ACCELERATION = 0.05 / 600
#: Range of the drift speed drawn from the seed for device, allpushed, rodgap and wide, nm/s.
NEW_SPEEDS = (0.15, 0.6)


@dataclass(frozen=True)
class Family:
    """One family: its side (nm), the objects drawn, its slots, electrodes and wire.

    ``particles`` and ``rods`` are the counts drawn; those near a slot, a pad or the wire
    are taken out. ``keep`` then keeps exactly so many particles and rods (the first
    clear ones as drawn), else every clear object is kept; ``kept_particles`` instead
    draws from the seed how many particles to keep (uniform integer in the range, no
    rods). With ``spare`` each kind of slot has more objects that fit it than slots, else
    at least as many. ``electrodes`` is the pads' gap and height (nm); ``speeds`` the
    range of the drift speed drawn when :func:`family_case` is given none; ``clearance``
    the least gap (nm) between a slot and an object.
    """

    name: str
    side: float
    particles: int
    layout: Slots
    rods: int = 0
    electrodes: Point | None = None
    keep: tuple[int, int] | None = None
    spare: bool = True
    rod_size: tuple[Point, Point] = ((500.0, 700.0), (60.0, 80.0))   # length and diameter ranges
    wire: bool = False
    speeds: Point = (DEFAULT_DRIFT, DEFAULT_DRIFT)
    #: Least distance (nm) from an object to the area's edge: the drift of a whole full
    #: scan, so that no object the layout needs is cut by the image border.
    border: float = 0.0
    clearance: float = SLOT_CLEARANCE
    kept_particles: tuple[int, int] | None = None

    def slots(self) -> tuple[Body, ...]:
        return self.layout(self.side / 2)

    def electrode_polygons(self) -> tuple[fs.Polygon, ...]:
        return () if self.electrodes is None else fs.electrodes(self.side, *self.electrodes)


FAMILIES: dict[str, Family] = {f.name: f for f in (
    Family("tiny", 1500.0, 5, fs.tiny),
    Family("sparse", 4000.0, 12, fs.ring(4)),
    Family("dense", 4000.0, 70, fs.ring(6), speeds=(DENSE_DRIFT, DENSE_DRIFT)),
    Family("rods", 4000.0, 10, fs.rod_between, rods=4),
    Family("mixed", 5000.0, 24, fs.bowtie, rods=3, electrodes=(1200.0, 600.0)),
    Family("device", 8000.0, 30, fs.device, rods=8, electrodes=(1400.0, 2000.0), keep=(12, 2),
           rod_size=((1150.0, 1300.0), (80.0, 100.0)), wire=True, speeds=NEW_SPEEDS, border=600.0),
    Family("allpushed", 6000.0, 24, fs.grid3, electrodes=(1600.0, 2000.0), keep=(9, 0), spare=False,
           speeds=NEW_SPEEDS, border=450.0),
    Family("rodgap", 10000.0, 0, fs.rod_row, rods=8, electrodes=(2400.0, 2000.0), keep=(0, 3),
           spare=False, rod_size=((1200.0, 1400.0), (90.0, 110.0)), speeds=NEW_SPEEDS, border=700.0),
    Family("wide", 16000.0, 130, fs.grid4x3, speeds=NEW_SPEEDS, border=1200.0, clearance=2000.0,
           kept_particles=(20, 60)),
)}


#: ``scaleN``: square side (nm) per square root of the object count, so the density stays
#: that of 1000 objects in 40 x 40 µm (the largest area a run full-scans, ``MAX_LAYOUT_SIDE``).
SCALE_SIDE = 40_000.0 / math.sqrt(1000.0)
#: ``scaleN``: slots per object.
SCALE_SLOTS = 0.3
#: ``scaleN``: the range of N.
SCALE_RANGE = (2, 1000)


def scale_family(n: int) -> Family:
    """``scaleN``: ``n`` particles at a constant density (:data:`SCALE_SIDE`) and
    ``round(0.3 n)`` particle slots in a square grid spread over the area, for scale
    benchmarks. The border is the drift of a whole full scan at :data:`DEFAULT_DRIFT`
    (10 nm pixels, 1 s lines: ``0.03 side``); enough particles are drawn that exactly ``n``
    stay clear of it and of the slots."""
    lo, hi = SCALE_RANGE
    if not lo <= n <= hi:
        raise ValueError(f"scene family scale{n}: N must be {lo}-{hi}")
    side = round(SCALE_SIDE * math.sqrt(n))
    border = round(DEFAULT_DRIFT * side / 10.0)
    count = max(1, round(SCALE_SLOTS * n))
    pitch = (side - 2.0 * border) / math.ceil(math.sqrt(count))
    return Family(f"scale{n}", float(side), math.ceil(1.3 * n) + 5, fs.array(count, pitch), keep=(n, 0),
                  border=float(border))


def family(name: str) -> Family:
    """The family called ``name`` (or ``scaleN``, :func:`scale_family`); ValueError listing
    the names otherwise."""
    try:
        return FAMILIES[name]
    except KeyError:
        if name.startswith("scale") and name[5:].isdigit() and name[5:] == str(int(name[5:])):
            return scale_family(int(name[5:]))
        raise ValueError(f"unknown scene family {name!r}; one of {', '.join(FAMILIES)} "
                         f"or scaleN (N = {SCALE_RANGE[0]}-{SCALE_RANGE[1]})") from None


def _enough(objects: tuple[Body, ...], slots: tuple[Body, ...], spare: int) -> bool:
    """At least ``spare`` more objects fit each kind of slot than there are such slots."""
    tol = Tolerance()
    return all(sum(size_ok(t, o, tol) for o in objects if o.kind == t.kind)
               >= sum(u.kind == t.kind for u in slots) + spare for t in slots)


def _kept(objects: tuple[Body, ...], keep: tuple[int, int] | None) -> tuple[Body, ...] | None:
    """The first ``keep`` particles and rods of ``objects`` in order; None if too few."""
    if keep is None:
        return objects
    want = {"particle": keep[0], "rod": keep[1]}
    out = []
    for o in objects:
        if want[o.kind] > 0:
            out.append(o)
            want[o.kind] -= 1
    return None if any(want.values()) else tuple(out)


def _clear_of(others: tuple[Body, ...], clearance: float):
    """A test whether a body keeps ``clearance`` nm from every one of ``others``."""
    geoms = np.array([o.geometry() for o in others], dtype=object)
    radii = np.array([o.radius for o in others], float)

    def clear(body: Body) -> bool:
        return bool(np.all(shapely.distance(body.geometry(), geoms) >= body.radius + radii + clearance))
    return clear


def _sig(x: float) -> float:
    """``x`` to 6 significant digits (short in a scene file, read back exactly)."""
    return float(f"{x:.6g}")


def _truth(fam: Family, seed: int) -> tuple[CreepParams, DriftChangeParams, float]:
    """The seed's creep and drift acceleration about nominal, and a drift speed in the
    family's range (always drawn, in this order, so one never shifts another)."""
    rng = np.random.default_rng([seed, 11])
    nominal = CreepParams()
    amplitude, tau = rng.uniform(1 - CREEP_SPREAD, 1 + CREEP_SPREAD, 2) * (nominal.amplitude, nominal.tau)
    magnitude, direction = rng.uniform(0.0, MAX_ACCELERATION), rng.uniform(0.0, 2.0 * math.pi)
    speed = float(rng.uniform(*fam.speeds))
    acceleration = (_sig(magnitude * math.cos(direction)), _sig(magnitude * math.sin(direction)))
    return (replace(nominal, amplitude=_sig(amplitude), tau=_sig(tau)),
            DriftChangeParams(acceleration=acceleration), speed)


def family_case(name: str, seed: int, drift: float | None = None) -> tuple[Scene, Layout]:
    """The scene and layout of family ``name`` for ``seed`` with ``drift`` nm/s of drift
    (None: the family's own, :data:`DEFAULT_DRIFT`, :data:`DENSE_DRIFT` or drawn from the seed).

    Raises
    ------
    ValueError
        For an unknown family, a negative seed or a drift that is negative or not finite.
    """
    fam = family(name)
    if seed < 0:
        raise ValueError(f"seed must not be negative, got {seed}")
    if drift is not None and not (math.isfinite(drift) and drift >= 0):
        raise ValueError(f"drift must be finite and >= 0 nm/s, got {drift!r}")
    creep, change, speed = _truth(fam, seed)
    keep = fam.keep
    if fam.kept_particles is not None:   # its own generator: no other draw shifts
        lo, hi = fam.kept_particles
        keep = (int(np.random.default_rng([seed, 17]).integers(lo, hi + 1)), 0)
    drift = speed if drift is None else drift
    direction = np.random.default_rng([seed, 7]).uniform(0.0, 2.0 * math.pi)
    velocity = (round(drift * math.cos(direction), 6), round(drift * math.sin(direction), 6))
    spec = SceneSpec(area=(fam.side, fam.side), particles=fam.particles, rods=fam.rods,
                     particle_diameter=(80.0, 100.0), rod_length=fam.rod_size[0],
                     rod_diameter=fam.rod_size[1], drift=DriftParams(velocity, DriftParams().random_walk))
    slots = fam.slots()
    polygons = fam.electrode_polygons()
    pads = shapely.union_all([shapely.Polygon(q) for q in polygons]) if polygons else None
    wires = (fs.wire(fam.side, fam.electrodes[1], np.random.default_rng([seed, 13])),) if fam.wire else ()

    inner = shapely.box(fam.border, fam.border, fam.side - fam.border, fam.side - fam.border)

    of_slots, of_wires = _clear_of(slots, fam.clearance), _clear_of(wires, spec.gap)

    def clear(o: Body) -> bool:
        return (of_slots(o) and of_wires(o)
                and (pads is None or shapely.distance(o.geometry(), pads) >= o.radius + spec.gap)
                and (fam.border == 0.0 or inner.contains(o.geometry().buffer(o.radius))))

    for attempt in range(ATTEMPTS):
        base = random_scene(spec, seed + 1_000_003 * attempt)
        kept = _kept(tuple(filter(clear, base.objects)), keep)
        if kept is not None and _enough(kept, slots, int(fam.spare)):
            break
    else:  # pragma: no cover - the families leave plenty of room
        raise RuntimeError(f"family {name}: no feasible scene for seed {seed} in {ATTEMPTS} attempts")
    obstacles = tuple(Obstacle(q, 30.0) for q in polygons)
    params = replace(base.params, creep=creep, drift_change=change, cantilever=draw_lever(seed))
    scene = replace(base, objects=kept + wires, obstacles=obstacles, params=params, seed=seed)
    scene = scene_from_dict(scene.to_dict(), f"family {name}")
    layout = Layout((fam.side, fam.side), slots, tuple(Keepout(q) for q in polygons), name=f"{name}-{seed}")
    return scene, layout_from_dict(layout.to_dict(), f"family {name}")
