"""Helpers for the simulated-AFM tests: scenes and streamed tip paths."""

from __future__ import annotations

import numpy as np
from nanoasm.bodies import Body
from nanoasm.instrument import ramp
from nanoasm.executor.estimators import NoDrift
from nanoasm.world.cantilever import tip_offset
from nanoasm.world.params import CreepParams, PushParams, VdwParams, WorldParams
from nanoasm.world.scene import Scene
from nanoasm.world.sim import SimulatedAFM, lever_from_params

#: No scatter in pivot and path, no van der Waals error, no creep: the model's own motion.
EXACT = WorldParams(push=PushParams(pivot_scatter=0.0, path_scatter=0.0), vdw=VdwParams(amplitude=0.0),
                    creep=CreepParams(amplitude=0.0))


def world(objects, *, area=(4000.0, 4000.0), params: WorldParams = EXACT, seed: int = 1, obstacles=()):
    # the scene's origin at the scanner's: sample and scanner frames agree at t = 0
    return SimulatedAFM(Scene(area, tuple(objects), tuple(obstacles), params, seed), placement=(0.0, 0.0))


class SteadyDrift(NoDrift):
    """A world's own steady drift, known exactly: the sample moves by ``v`` nm/s in the
    scanner's frame (offset = v t)."""

    def __init__(self, v):
        super().__init__((0.0, 0.0), 0.0)
        self.v = np.asarray(v, float)

    def offset(self, t: float) -> np.ndarray:
        return self.origin + self.v * t


def particle(at, d=50.0, id="p1") -> Body:
    return Body(id, "particle", (float(at[0]), float(at[1])), float(d))


def rod(at, angle, length, d=50.0, id="r1") -> Body:
    return Body(id, "rod", (float(at[0]), float(at[1])), float(d), float(angle), float(length))


def preload_offset(sim: SimulatedAFM) -> np.ndarray:
    """XY (nm) by which the tip under the preload sits off the piezo (eq. 3.30-3.34)."""
    p = sim.params
    lever = lever_from_params(p)
    return tip_offset(p.scanner.preload / p.cantilever.K_n, 0.0, p.scanner.scan_angle, lever)[:2]


def path_codes(sim: SimulatedAFM, points, push_speed: float = 200.0) -> np.ndarray:
    """Codes from the instrument's position through ``points`` (scanner nm, XYZ): at the
    push speed between two points in contact, at full speed otherwise."""
    cfg = sim.config
    cur = sim.position()
    out = []
    for i, p in enumerate(points):
        c = cfg.nm_to_codes(np.asarray(p, float))
        pushing = i > 0 and p[2] < 0 and points[i - 1][2] < 0
        out.append(ramp(cur, c, cfg, speed=push_speed if pushing else None))
        cur = c
    return np.vstack(out)


def push(sim: SimulatedAFM, start, end, *, compensate: bool = True, lift: float | None = None,
         push_speed: float = 200.0):
    """Travel lifted to ``start``, lower to the preload, push to ``end``, lift. Tip targets
    in the sample frame at time ~0 (drift ignored); the piezo is offset so the deflected
    tip lands on them when ``compensate``. Returns the SignalBlock and the codes."""
    cfg = sim.config
    off = preload_offset(sim) if compensate else np.zeros(2)
    lift = cfg.lift if lift is None else lift
    (x0, y0), (x1, y1) = np.asarray(start, float) - off, np.asarray(end, float) - off
    codes = path_codes(sim, [(x0, y0, lift), (x0, y0, -cfg.preload), (x1, y1, -cfg.preload),
                             (x1, y1, lift)], push_speed)
    return sim.write(codes), codes


class Events:
    """A dry-run subscriber keeping the texts of its events."""

    def __init__(self):
        self.texts: list[str] = []

    def __call__(self, topic, doc):
        if topic == "event":
            self.texts.append(doc.text if hasattr(doc, "text") else doc["text"])
