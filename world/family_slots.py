"""Slot layouts, electrodes and fixed wires of the generated scene families.

A slot layout is a function of the centre ``c`` of the family's square area (nm) giving
the layout's targets. :func:`electrodes` draws a pair of rectangular pads facing each
other across a gap centred in the area, from the area's left and right edges; the
families put them in the scene as obstacles and in the layout as keep-outs.
:func:`wire` places a wire (a rod with L/d > 25, which the simulator bends and
identification calls ``wire``) above or below the pads, far from every slot.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from nanoasm.bodies import Body
from nanoasm.schema import Point

PARTICLE_SLOT = 90.0
ROD_SLOT = (600.0, 70.0)          # length, diameter
#: The rod slot across the gap of ``device``; the rod slots of ``rodgap``.
DEVICE_ROD_SLOT = (1200.0, 90.0)
RODGAP_SLOT = (1300.0, 100.0)
#: The wire of ``device``: length and diameter (L/d = 30).
WIRE = (2700.0, 90.0)

Slots = Callable[[float], tuple[Body, ...]]
Polygon = tuple[Point, ...]


def _particle(i: int, x: float, y: float) -> Body:
    return Body(f"s{i}", "particle", (x, y), PARTICLE_SLOT)


def _rod(name: str, x: float, y: float, angle: float, size: tuple[float, float]) -> Body:
    return Body(name, "rod", (x, y), size[1], angle, size[0])


def tiny(c: float) -> tuple[Body, ...]:
    """A dimer."""
    return _particle(1, c - 60, c), _particle(2, c + 60, c)


def rod_between(c: float) -> tuple[Body, ...]:
    """A rod slot between two particle slots, in line."""
    reach = ROD_SLOT[0] / 2 + PARTICLE_SLOT / 2 + 40
    return _rod("bar", c, c, 0.0, ROD_SLOT), _particle(1, c - reach, c), _particle(2, c + reach, c)


def bowtie(c: float) -> tuple[Body, ...]:
    """Four particle slots between the pads of ``mixed``, a rod slot below."""
    return (_particle(1, c - 200, c - 100), _particle(2, c - 200, c + 100),
            _particle(3, c + 200, c - 100), _particle(4, c + 200, c + 100),
            _rod("bar", c, c - 900, 0.0, ROD_SLOT))


def ring(n: int) -> Slots:
    """``n`` particle slots on a circle, neighbours 150 nm apart."""
    r = 150 / (2 * math.sin(math.pi / n))

    def slots(c: float) -> tuple[Body, ...]:
        return tuple(_particle(i + 1, c + r * math.cos(2 * math.pi * i / n + math.pi / n),
                               c + r * math.sin(2 * math.pi * i / n + math.pi / n)) for i in range(n))
    return slots


def device(c: float) -> tuple[Body, ...]:
    """A rod across the gap (along x, 100 nm clear of each pad of a 1400 nm gap) and four
    particle slots above it and four below, 60 nm clear of it, 210 nm of each other."""
    dy = DEVICE_ROD_SLOT[1] / 2 + 60 + PARTICLE_SLOT / 2
    xs = (c - 450, c - 150, c + 150, c + 450)
    return (_rod("bar", c, c, 0.0, DEVICE_ROD_SLOT),
            *(_particle(i + 1, x, c + dy) for i, x in enumerate(xs)),
            *(_particle(i + 5, x, c - dy) for i, x in enumerate(xs)))


def grid(nx: int, ny: int, pitch: float) -> Slots:
    """``nx`` x ``ny`` particle slots in a grid of ``pitch`` nm centred on the area's
    centre, numbered along x first."""
    def slots(c: float) -> tuple[Body, ...]:
        return tuple(_particle(nx * j + i + 1, c + pitch * (i - (nx - 1) / 2), c + pitch * (j - (ny - 1) / 2))
                     for j in range(ny) for i in range(nx))
    return slots


def array(count: int, pitch: float) -> Slots:
    """``count`` particle slots, the first of a square grid of ``pitch`` nm (as many columns
    as rows, the last row partly filled) centred on the area's centre, numbered along x first."""
    cols = math.ceil(math.sqrt(count))
    rows = math.ceil(count / cols)

    def slots(c: float) -> tuple[Body, ...]:
        return tuple(_particle(k + 1, c + pitch * (k % cols - (cols - 1) / 2), c + pitch * (k // cols - (rows - 1) / 2))
                     for k in range(count))
    return slots


#: ``allpushed``: nine particle slots in a 3 x 3 grid of 150 nm pitch.
grid3 = grid(3, 3, 150.0)
#: ``wide``: twelve particle slots in a 4 x 3 grid of 300 nm pitch (210 nm clear between
#: neighbours: room for the tip to pass).
grid4x3 = grid(4, 3, 300.0)


def rod_row(c: float) -> tuple[Body, ...]:
    """Three parallel rod slots along y, 400 nm apart (300 nm clear)."""
    return tuple(_rod(f"bar{k + 1}", c + 400 * (k - 1), c, 90.0, RODGAP_SLOT) for k in range(3))


def electrodes(side: float, gap: float, height: float) -> tuple[Polygon, Polygon]:
    """Left and right pads, ``height`` tall, from the area's edges to a ``gap`` centred in it."""
    c = side / 2
    lo, hi = c - height / 2, c + height / 2
    left = ((0.0, lo), (c - gap / 2, lo), (c - gap / 2, hi), (0.0, hi))
    right = ((c + gap / 2, lo), (side, lo), (side, hi), (c + gap / 2, hi))
    return left, right


def wire(side: float, height: float, rng: np.random.Generator) -> Body:
    """The ``WIRE`` lying roughly along x above or below pads ``height`` tall (at least
    800 nm from them and from the area's edge, 600 nm beyond its ends), within 10° of
    the x axis."""
    length, d = WIRE
    c = side / 2
    below = rng.random() < 0.5
    y = rng.uniform(c + height / 2 + 800, side - 800)
    x = rng.uniform(length / 2 + 700, side - length / 2 - 700)
    angle = rng.uniform(-10.0, 10.0)
    at = (round(float(x), 3), round(float(side - y if below else y), 3))
    return Body("w1", "rod", at, d, round(float(angle) % 180.0, 3), length)
