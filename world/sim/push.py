"""Pushing physics of the simulated AFM, one DAC sample at a time, only near objects.

A *push* starts when the tip, in contact with the substrate, first touches an object; it
lasts while the tip stays within the contact distance (plus ``[sim] release`` nm), and ends
when the tip lifts or leaves. At its start the push's faults are drawn
(:mod:`nanoasm.world.sim.faults`) and its outcome decided by the seed's equilibrium
(eq. 4.6-4.7 for particles and wires, 4.19-4.20 for rods, every step as the contact
slides): with the normal force F_z below F̄z, or θ ≥ θmax, the tip *rides* over the
object (slips over it) and the object stays.

Motion per step (tip from ``p0`` to ``p1``, sample frame, nm):

- particle (seed §4.2): translates. While the contact normal lies within
  ``[sim] capture_angle`` of the tip's motion (tip–object friction and the apex's size hold it,
  the seed's pushes over microns) it moves along the tip's motion turned by its own path
  error, back to the contact distance; outside that cone it slides round the tip along
  the contact normal, frictionless (:func:`~nanoasm.world.particle_push.particle_step`),
  and is soon lost;
- rod: :func:`~nanoasm.world.sim.rods.rod_motion`; wire:
  :func:`~nanoasm.world.sim.rods.wire_motion`;
- a stuck object, or one that would enter an obstacle (deeper than it lies in one: it may
  leave one it lies against), does not move: the lateral force
  rises by the lever's stiffness (``lateral_gain / C1``) times the piezo's overshoot until
  its vertical part lifts the tip over the object.

The lateral force on the tip (:meth:`PushPhysics.step`) is a vector: the object's contact
force (eq. 4.4's ``(F^r_to - F^a_to) cos θ``) along the contact normal, from the object's
nearest core point to the tip, plus the tip–substrate friction on the excess load
(``μts (F_z - F̄z)``) against the tip's motion. A particle pushed off-centre thus twists
the lever towards its side, as it does a real one (issue 13: what in-push tracking reads).

What an object shoves moves through :class:`~nanoasm.world.sim.contacts.SimContacts`;
when a push ends, each moved object that ends near another gets the random van der Waals
error of ``[vdw]`` (seed 3.6.1), once. Forces in nN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from nanoasm.world.particle_push import PushOutcome, particle_step, push_force_parts, push_outcome
from nanoasm.world.pivot import rho, rod_push_outcome

from .faults import PushFaults, draw_push_faults
from .objects import Kind
from .push_support import PushWorld
from .rods import rod_motion, wire_motion
from .wire import affect_radius

#: A tip step shorter than this (nm; drift alone, or a Z-only move) pushes nothing.
STILL = 1e-3

PUSH, RIDE, GONE = "push", "ride", "gone"




def _heading(ep: "Episode", p0, p1, length: float) -> tuple[float, float]:
    """Unit direction of the tip's motion over the last ``length`` nm of its path (from a
    point that trails the tip by that much, or from where the push began): a path drawn
    by a DAC is a staircase of single-axis code steps, and the object follows the path,
    not each stair (``[sim] heading_length``)."""
    if ep.trail is None:
        ep.trail = (float(p0[0]), float(p0[1]))
    dx, dy = p1[0] - ep.trail[0], p1[1] - ep.trail[1]
    d = math.hypot(dx, dy)
    if d == 0.0:
        return ep.heading if ep.heading is not None else (0.0, 0.0)
    ep.heading = (dx / d, dy / d)
    if d > length:
        ep.trail = (p1[0] - ep.heading[0] * length, p1[1] - ep.heading[1] * length)
    return ep.heading


@dataclass
class Episode:
    """The state of one push of one object."""

    mode: str
    faults: PushFaults
    theta: float = 0.0        # θ = θx + γ, deg
    f_push: float = 0.0       # lateral force while it moves, nN (particles and wires)
    f_fric: float = 0.0       # its tip–substrate friction part μts (F_z - F̄z), nN
    branch: int = 1
    travelled: float = 0.0    # nm the tip moved while pushing
    moved: set[int] = field(default_factory=set)
    heading: tuple[float, float] | None = None   # the tip's direction of motion
    trail: tuple[float, float] | None = None     # a point HEADING_LENGTH behind the tip


class PushPhysics(PushWorld):
    """Objects, their contacts and the pushes in progress; :meth:`step` plays one sample."""

    def step(self, objs, p0: tuple[float, float], p1: tuple[float, float], f_z: float, theta: float,
             lifting: bool = False, lag: tuple[float, float] = (0.0, 0.0)):
        """The tip moves from ``p0`` to ``p1`` in contact with normal force ``f_z`` (nN).

        ``objs`` are the objects near the tip. Returns ``(pushing, force, ride)``:
        whether an object resists the tip, the lateral force ``(fx, fy)`` (nN) the
        objects put on the tip (contact normal and friction, see the module's text) and
        the height (nm) the apex rides over an object. A tip
        that is ``lifting`` (unloading) or does not move pushes nothing. ``lag`` (nm) is
        the part of the tip's offset from the piezo that the lateral force causes.
        """
        pushing, fx, fy, ride = False, 0.0, 0.0, 0.0
        self.lag = lag
        self.steps += 1
        ds = math.hypot(p1[0] - p0[0], p1[1] - p0[1])
        if lifting or ds < STILL:
            for o in objs:
                ep = self.episodes.get(int(o))
                if ep is not None and ep.mode == RIDE:
                    ride = max(ride, self.ride_height(int(o), p1))
            return pushing, (fx, fy), ride
        motion = ((p1[0] - p0[0]) / ds, (p1[1] - p0[1]) / ds)
        for o in objs:
            p, f, h = self._step_object(int(o), p0, p1, f_z, theta)
            pushing |= p
            if f != 0.0:
                gx, gy = self._force(int(o), p1, motion, f)
                fx += gx
                fy += gy
            ride = max(ride, h)
        return pushing, (fx, fy), ride

    def _force(self, o: int, p1, motion, magnitude: float) -> tuple[float, float]:
        """The lateral force (nN) of ``magnitude`` that object ``o`` puts on the tip at
        ``p1``: its friction part against the tip's ``motion``, the rest along the contact
        normal (from the object's nearest core point to the tip)."""
        ep = self.episodes.get(o)
        ff = min(ep.f_fric, magnitude) if ep is not None else 0.0
        (nx, ny), _ = self.normal(o, p1)
        fc = magnitude - ff
        return -nx * fc - motion[0] * ff, -ny * fc - motion[1] * ff

    def end_all(self) -> None:
        """End every push in progress (the tip lifted or left)."""
        for o in sorted(self.episodes):
            self._finish(o)

    # -- one object ------------------------------------------------------------------------------
    def _step_object(self, o: int, p0, p1, f_z: float, theta: float):
        gap1 = self.gap(o, p1)
        ep = self.episodes.get(o)
        if ep is None:
            if gap1 >= 0.0:
                return False, 0.0, 0.0
            ep = self._start(o, p0, f_z, theta)
        if ep.mode == GONE:
            return False, 0.0, 0.0
        if ep.mode == RIDE:
            if gap1 > self.release:
                self._finish(o)
                return False, 0.0, 0.0
            return False, 0.0, self.ride_height(o, p1)
        if gap1 > self.release:
            self._finish(o)
            return False, 0.0, 0.0
        kind = self.table.kind[o]
        if kind == Kind.PARTICLE:
            return self._particle(o, ep, p0, p1, f_z)
        if kind == Kind.ROD:
            return self._rod(o, ep, p0, p1, f_z)
        return self._wire(o, ep, p0, p1, f_z)

    def _start(self, o: int, p0, f_z: float, theta: float) -> Episode:
        t = self.table
        rc = self.radius(o) + self.tip_radius
        faults = draw_push_faults(self.faults, rc, self.rng_faults)
        branch = 1 if self.rng_faults.random() < 0.5 else -1
        ep = Episode(PUSH, faults, theta, branch=branch)
        self.episodes[o] = ep
        if self.gap(o, p0) < 0.0:          # lowered onto it: the tip sits on the object
            ep.mode = RIDE
            return ep
        if faults.blunt:
            self.tip_radius += self.faults.blunting_step
            self.blunted += 1
        if faults.lost:
            self.jump(o, faults.jump)
            ep.mode = GONE
        elif t.kind[o] != Kind.ROD:
            f_os = t.f_os_a[o] * self._wire_share(o)
            out = push_outcome(f_z, theta, t.mu_os[o], t.nu[o], f_os, self.f_ts, 1.0)
            if out is not PushOutcome.MOVES:
                ep.mode = RIDE
                self.slips += 1
            else:
                fc, ff = push_force_parts(theta, t.mu_os[o], t.nu[o], f_os, self.f_ts, f_z, self.mu_ts)
                ep.f_push = float(fc + ff)
                ep.f_fric = ep.f_push - float(fc)
        return ep

    def _affect(self, b) -> float:
        """Radius (nm) of the region of wire ``b`` a push bends."""
        return affect_radius(b.length, b.diameter, self.sim.wire_affect_fraction, self.sim.wire_affect_min)

    def _wire_share(self, o: int) -> float:
        if self.table.kind[o] != Kind.WIRE:
            return 1.0
        b = self.table.bodies[o]
        return min(1.0, 2.0 * self._affect(b) / b.length)

    def _blocked(self, o: int, ep: Episode, p1, f_push: float, f_z: float):
        """The object does not move: the force grows with the piezo's overshoot (the tip's
        penetration plus what the lever's twist already holds it back, ``self.lag``) until
        its vertical part lifts the tip over the object."""
        (nx, ny), pen = self.normal(o, p1)
        overshoot = pen - (self.lag[0] * nx + self.lag[1] * ny)
        f = f_push + self.k_stick * max(overshoot, 0.0)
        th = math.radians(ep.theta)
        if f * math.sin(th) - self.f_ts > f_z:
            ep.mode = RIDE
            self.slips += 1
            return False, 0.0, 0.0
        return True, f * math.cos(th), 0.0

    def _hold(self, o: int, ep: Episode, p1, f_z: float):
        """The tip, held back by its own twist (``self.lag``), does not reach the object: the
        lever still presses it if the untwisted tip would (static contact, no motion)."""
        q = (p1[0] - self.lag[0], p1[1] - self.lag[1])
        if self.gap(o, q) >= 0.0:
            return False, 0.0, 0.0
        if ep.faults.stuck:
            return self._blocked(o, ep, p1, ep.f_push, f_z)
        return True, ep.f_push, 0.0

    def _slipped(self, ep: Episode, p0, p1) -> bool:
        ep.travelled += math.hypot(p1[0] - p0[0], p1[1] - p0[1])
        if ep.travelled > ep.faults.slip_after:
            ep.mode = RIDE
            self.slips += 1
            return True
        return False

    # -- kinds -----------------------------------------------------------------------------------
    def _particle(self, o: int, ep: Episode, p0, p1, f_z: float):
        u = int(self.table.first_unit[o])
        x, y = self.contacts.unit(u).at
        d = 2.0 * self.radius(o)
        rc = 0.5 * d + self.tip_radius
        gx, gy = x - p1[0], y - p1[1]
        dist = math.hypot(gx, gy)
        if dist >= rc:
            return self._hold(o, ep, p1, f_z)
        if ep.faults.stuck:
            return self._blocked(o, ep, p1, ep.f_push, f_z)
        if self._slipped(ep, p0, p1):
            return False, 0.0, self.ride_height(o, p1)
        sx, sy = p1[0] - p0[0], p1[1] - p0[1]
        ds = math.hypot(sx, sy)
        nx, ny, _ = particle_step(x, y, d, p0[0], p0[1], sx, sy, self.tip_radius)
        hx, hy = _heading(ep, p0, p1, self.sim.heading_length)
        if ds > 0.0 and (gx * hx + gy * hy) >= math.cos(math.radians(self.sim.capture_angle)) * dist:
            mx, my = hx, hy                                            # carried along the motion
            b = gx * mx + gy * my
            adv = -b + math.sqrt(max(b * b - dist * dist + rc * rc, 0.0))
            e = math.radians(self.table.path_error[o])
            ce, se = math.cos(e), math.sin(e)
            nx, ny = x + adv * (ce * mx - se * my), y + adv * (se * mx + ce * my)
            qx, qy = nx - p1[0], ny - p1[1]
            q = math.hypot(qx, qy)
            if 0.0 < q < rc:
                nx, ny = p1[0] + qx * rc / q, p1[1] + qy * rc / q
        body = self.contacts.unit(u)
        moved_body = type(body)(body.id, body.kind, (nx, ny), body.diameter)
        if self.hits_obstacle(moved_body, body):
            return self._blocked(o, ep, p1, ep.f_push, f_z)
        ep.moved.update(self.contacts.push(u, (nx - x, ny - y)))
        self.after_shove(ep.moved, o)
        return True, ep.f_push, 0.0

    def _rod(self, o: int, ep: Episode, p0, p1, f_z: float):
        t = self.table
        u = int(t.first_unit[o])
        body = self.contacts.unit(u)
        if ep.faults.stuck:
            return self._blocked(o, ep, p1, ep.f_push, f_z) if self.gap(o, p1) < 0 else self._hold(o, ep, p1, f_z)
        motion = rod_motion(body, p0, p1, tip_radius=self.tip_radius, branch=ep.branch,
                            band=self.sim.bifurcation_band,
                            pivot_offset=float(t.pivot_offset[o]))
        if motion.body is None:
            if self.gap(o, p1) < 0.0:       # past or over an end: the tip rides over the cap
                ep.mode = RIDE
                return False, 0.0, self.ride_height(o, p1)
            return self._hold(o, ep, p1, f_z)
        L = body.length
        out = rod_push_outcome(f_z, motion.l, L, ep.theta, t.mu_os[o], t.nu[o], t.f_os_a[o], self.f_ts)
        if out is not PushOutcome.MOVES:
            ep.mode = RIDE
            self.slips += 1
            return False, 0.0, self.ride_height(o, p1)
        fc, ff = push_force_parts(ep.theta, t.mu_os[o], t.nu[o], t.f_os_a[o], self.f_ts, f_z, self.mu_ts,
                                  float(rho(motion.l, L)))
        f_lat = float(fc + ff)
        ep.f_push, ep.f_fric = f_lat, f_lat - float(fc)
        if self.hits_obstacle(motion.body, body):
            return self._blocked(o, ep, p1, f_lat, f_z)
        if self._slipped(ep, p0, p1):
            return False, 0.0, self.ride_height(o, p1)
        self.contacts.place(u, motion.body)
        ep.moved.add(u)
        ep.moved.update(self.contacts.settle(u, (p1[0] - p0[0], p1[1] - p0[1])))
        self.after_shove(ep.moved, o)
        self.version += 1
        return True, f_lat, 0.0

    def _wire(self, o: int, ep: Episode, p0, p1, f_z: float):
        b = self.table.bodies[o]
        if ep.faults.stuck:
            return self._blocked(o, ep, p1, ep.f_push, f_z) if self.gap(o, p1) < 0 else self._hold(o, ep, p1, f_z)
        nodes = wire_motion(self.wires[o], b.diameter, p1, tip_radius=self.tip_radius,
                            affect=self._affect(b),
                            step=(p1[0] - p0[0], p1[1] - p0[1]))
        if nodes is None:
            return self._hold(o, ep, p1, f_z)
        if self.wire_hits_obstacle(o, nodes):
            return self._blocked(o, ep, p1, ep.f_push, f_z)
        if self._slipped(ep, p0, p1):
            return False, 0.0, self.ride_height(o, p1)
        ep.moved.update(self.place_wire(o, nodes, (p1[0] - p0[0], p1[1] - p0[1])))
        self.after_shove(ep.moved, o)
        return True, ep.f_push, 0.0

    # -- the end of a push ----------------------------------------------------------------------
    def _finish(self, o: int) -> None:
        ep = self.episodes.pop(o, None)
        if ep is None or not ep.moved:
            return
        self.pushes += 1
        objs = sorted({int(self.contacts.groups[u]) for u in ep.moved})
        for m in objs:
            if self.vdw.amplitude > 0 and self.near_other(m):
                ex, ey = self.rng_vdw.normal(0.0, self.vdw.amplitude, size=2)
                self.translate(m, (float(ex), float(ey)))
