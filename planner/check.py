"""An independent check of a plan: replay every push in order and look for collisions.

It shares nothing with the planner but the value types: each push moves its object from
where it is to the push's ``expect`` pose (particles along the push line, rods turning
about the fixed point of that rigid motion), and the swept footprint is tested with
plain shapely against keep-outs, obstacles and every other object where it is at that
moment. The tip's own path is tested too: where it is put down it must not land on
another object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import shapely

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout
from nanoasm.world.environment import Environment

from .plan import Operation, Plan

#: Penetration, nm, below which two footprints count as touching.
SLACK = 1e-6


@dataclass(frozen=True)
class Collision:
    operation: int
    object: str
    hit: str          # "keepout[2]", "obstacle[1]", an object id, or "area"
    overlap: float    # nm² of new overlap

    def __str__(self) -> str:
        return f"operation {self.operation}: {self.object} hits {self.hit} ({self.overlap:.2f} nm² overlap)"


def _poses(before: Body, op: Operation) -> list[Body]:
    """Poses of the pushed object during the push, a few degrees or a radius apart."""
    if before.kind != "rod":
        after = Body(before.id, before.kind, op.expect.at, before.diameter)
        return [before, after]
    angle = op.expect.angle if op.expect.angle is not None else before.angle
    turn = math.remainder(angle - before.angle, 180.0)
    end = before.angle + turn
    th = math.radians(turn)
    n = max(1, math.ceil(abs(turn) / 1.0), math.ceil(math.dist(before.at, op.expect.at) / before.radius))
    if abs(th) < 1e-9:
        return [Body(before.id, "rod", (before.at[0] + (op.expect.at[0] - before.at[0]) * k / n,
                                        before.at[1] + (op.expect.at[1] - before.at[1]) * k / n),
                     before.diameter, before.angle, before.length) for k in range(n + 1)]
    c, s = math.cos(th), math.sin(th)
    ax, ay = before.at
    bx, by = op.expect.at
    rx, ry = bx - (c * ax - s * ay), by - (s * ax + c * ay)
    det = (1 - c) ** 2 + s * s
    px, py = ((1 - c) * rx - s * ry) / det, (s * rx + (1 - c) * ry) / det
    out = []
    for k in range(n + 1):
        t = th * k / n
        ct, st = math.cos(t), math.sin(t)
        out.append(Body(before.id, "rod", (px + ct * (ax - px) - st * (ay - py), py + st * (ax - px) + ct * (ay - py)),
                        before.diameter, before.angle + math.degrees(t), before.length))
    out[-1] = Body(before.id, "rod", op.expect.at, before.diameter, end, before.length)
    return out


def _footprint(b: Body) -> shapely.Geometry:
    return b.geometry().buffer(b.radius, quad_segs=16)


def check_plan(plan: Plan, layout: Layout, env: Environment, *, tip_radius: float = 10.0) -> list[Collision]:
    """Collisions found by replaying ``plan`` from the objects of ``env`` (empty: none).

    An object that starts overlapping a keep-out or obstacle may leave it; only a push that
    makes such an overlap deeper, or creates one, counts.
    """
    objects = {o.id: Body(o.id, o.kind, o.at, o.diameter, o.angle, o.length) for o in env.objects}
    regions = [(f"keepout[{i}]", k.geometry()) for i, k in enumerate(layout.keepouts, start=1)]
    regions += [(f"mark[{i}]", k.geometry()) for i, k in enumerate(layout.marks, start=1)]
    regions += [(f"obstacle[{i}]", shapely.Polygon(ob.polygon)) for i, ob in enumerate(env.obstacles, start=1)]
    area = shapely.box(0, 0, min(layout.area[0], env.area[0]), min(layout.area[1], env.area[1]))
    found: list[Collision] = []
    for op in plan.operations:
        body = objects[op.object]
        poses = _poses(body, op)
        sweep = shapely.union_all([_footprint(p) for p in poses])
        start = _footprint(body)
        for name, poly in regions:
            depth = sweep.intersection(poly).area - start.intersection(poly).area
            if depth > SLACK:
                found.append(Collision(op.id, op.object, name, depth))
        outside = sweep.difference(area).area - start.difference(area).area
        if outside > SLACK:
            found.append(Collision(op.id, op.object, "area", outside))
        tip = shapely.Point(op.tip_path[0]).buffer(tip_radius)
        for other in objects.values():
            if other.id == op.object:
                continue
            fp = _footprint(other)
            depth = sweep.intersection(fp).area - start.intersection(fp).area
            if depth > SLACK:
                found.append(Collision(op.id, op.object, other.id, depth))
            elif tip.intersection(fp).area > SLACK:
                found.append(Collision(op.id, f"tip of {op.object}", other.id, tip.intersection(fp).area))
        objects[op.object] = poses[-1]
    return found
