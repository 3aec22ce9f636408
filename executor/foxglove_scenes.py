"""What the run log draws for Foxglove: log lines, the full scan as a grid, and scenes of
bodies, tip paths and the layout (Foxglove's well-known protobuf messages).

Free functions from documents (dicts as the run log keeps them) to messages, stamped
with the instrument time in nanoseconds; :class:`~nanoasm.executor.runlog.RunLog`
writes them. Positions in nm in the layout frame (``frame_id`` ``"layout"``); Foxglove's
3-D panel shows 1 nm as 1 m. The full scan as a 3-D surface is :mod:`.scan_surface`'s.
"""

from __future__ import annotations

import math

import numpy as np

from .json_parts import Kept

#: Colours (r, g, b, a) of what the scenes draw.
COLOURS = {
    "target": (0.2, 0.6, 1.0, 1.0),
    "keepout": (1.0, 0.3, 0.3, 1.0),
    "area": (0.6, 0.6, 0.6, 1.0),
    "object": (1.0, 0.8, 0.2, 1.0),
    "belief": (0.3, 0.9, 0.4, 0.9),
    "plan": (0.6, 0.6, 1.0, 0.6),
    "ok": (0.2, 0.9, 0.3, 1.0),
    "failed": (1.0, 0.2, 0.2, 1.0),
    "scan": (1.0, 1.0, 1.0, 1.0),
}

_LEVELS = {"debug": "Debug", "info": "Info", "warn": "Warning", "warning": "Warning",
           "error": "Error", "fatal": "Fatal"}


def nanoseconds(t: float | None) -> int:
    """A log time: instrument seconds in ns (0 for none, or before the start)."""
    return int(round(max(float(t), 0.0) * 1e9)) if t is not None and math.isfinite(t) else 0


def timestamp(ns: int):
    from foxglove.messages import Timestamp

    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def log_line(stamp, level: str, text: str):
    """A ``foxglove.Log`` line; ``level`` debug, info, warn(ing), error or fatal."""
    from foxglove.messages import Log, LogLevel

    return Log(timestamp=stamp, level=getattr(LogLevel, _LEVELS.get(level, "Info")), message=text, name="nanoasm")


def grid(doc: dict, stamp):
    """The full scan (``height``, ``pixel_size``, ``origin``) as a float32 ``foxglove.Grid``."""
    from foxglove.messages import (Grid, PackedElementField, PackedElementFieldNumericType, Pose,
                                   Quaternion, Vector2, Vector3)

    h = np.ascontiguousarray(np.asarray(doc["height"], dtype="<f4"))
    ny, nx = h.shape
    px = float(doc["pixel_size"])
    ox, oy = (float(v) for v in doc.get("origin", (0.0, 0.0)))
    return Grid(timestamp=stamp, frame_id="layout",
                pose=Pose(position=Vector3(x=ox, y=oy, z=0.0), orientation=Quaternion(w=1.0)),
                column_count=nx, cell_size=Vector2(x=px, y=px), row_stride=4 * nx, cell_stride=4,
                fields=[PackedElementField(name="height", offset=0,
                                           type=PackedElementFieldNumericType.Float32)],
                data=h.tobytes())


def bodies_scene(bodies, prefix: str, colour, stamp, delete=(), lift=None, memo: dict | None = None) -> bytes:
    """Bodies (``Body.to_dict()`` documents): particles as spheres, rods and wires as
    boxes along their axis, with their ids, each as entity ``prefix:id``; the entities
    ``prefix:id`` of ``delete`` removed. Each rests on z = 0, or on ``lift(body)`` (nm).
    The encoded ``foxglove.SceneUpdate`` (protobuf; the run log's channels take it as it
    is): each body's entity is encoded once by its pose and kept, and the message is those
    bytes with ``stamp`` put before each (a checkpoint draws a thousand bodies, most of
    them as they were). The bytes are the message's own encoding (a test builds it).
    ``memo``: a dict the caller keeps from one call to the next with the same ``prefix``,
    ``colour`` and ``lift``: a body that is the very same unchanging part
    (:class:`~.json_parts.Kept`) as in the last call is drawn as then, not lifted again."""
    from foxglove.messages import SceneEntity, SceneEntityDeletion, SceneUpdate
    head = SceneEntity(timestamp=stamp).encode()        # field 1, the first an entity's encoding holds
    parts, drawn = [], {}
    for b in bodies:
        hit = memo.get(id(b)) if memo is not None and type(b) is Kept else None
        if hit is None or hit[0] is not b:
            hit = _drawn(b, prefix, colour, lift)
            if hit is None:
                continue
        if memo is not None and type(b) is Kept:
            drawn[id(b)] = hit
        parts.append(_ENTITIES + _varint(len(head) + len(hit[1])) + head + hit[1])
    if memo is not None:
        memo.clear()
        memo.update(drawn)
    deletions = [SceneEntityDeletion(timestamp=stamp, id=f"{prefix}:{i}") for i in delete]
    return SceneUpdate(deletions=deletions).encode() + b"".join(parts)   # field 1, deletions, comes first


#: The key of ``SceneUpdate.entities`` (field 2, length-delimited).
_ENTITIES = b"\x12"


def _varint(n: int) -> bytes:
    """Protobuf's base-128 varint of ``n`` >= 0."""
    out = bytearray()
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _drawn(b, prefix: str, colour, lift) -> tuple | None:
    """(``b``, its entity encoded without a timestamp) of :func:`bodies_scene`; None for a
    body without a position or size."""
    try:
        x, y = (float(v) for v in b["at"])
        d = float(b["diameter"])
    except (KeyError, TypeError, ValueError):
        return None
    z = lift(b) if lift is not None else 0.0
    length, angle = b.get("length"), b.get("angle")
    key = (prefix, tuple(colour), str(b.get("id", "")), x, y, d, z,
           *((float(length), float(angle)) if length is not None and angle is not None else ()))
    body = _BODIES.get(key)
    if body is None:
        if len(_BODIES) >= BODIES_KEPT:
            _BODIES.clear()
        body = _BODIES[key] = _entity_bytes(key)
    return b, body


#: A body's entity encoded without its timestamp, by (prefix, colour, id, x, y, diameter, z[,
#: length, angle]): a run log draws every body after every push (twice: ``/belief`` and the
#: 3-D view), and between two pushes most have not moved (a 1000-object run: 10 s of its
#: compute to make their primitives anew, 6 ms a push to make and encode their entities).
_BODIES: dict[tuple, bytes] = {}
BODIES_KEPT = 50_000


def _entity_bytes(key: tuple) -> bytes:
    """The ``SceneEntity`` of :func:`bodies_scene`'s ``key``, encoded, without a timestamp."""
    from foxglove.messages import SceneEntity

    text, shapes = _shapes(key[1:])
    return SceneEntity(frame_id="layout", id=f"{key[0]}:{key[2]}", texts=[text], **shapes).encode()


def _shapes(key: tuple) -> tuple:
    """(label, {"spheres" or "cubes": [primitive]}) of a body drawn by :func:`bodies_scene`:
    ``key`` is (colour, id, x, y, diameter, z[, length, angle])."""
    from foxglove.messages import Color, CubePrimitive, SpherePrimitive, TextPrimitive, Vector3

    colour, ident, x, y, d, z, *rod = key
    col = Color(r=colour[0], g=colour[1], b=colour[2], a=colour[3])
    text = TextPrimitive(pose=_pose(x, y, z + d), billboard=True, font_size=12.0, scale_invariant=True,
                         color=col, text=ident)
    if rod:
        return text, {"cubes": [CubePrimitive(pose=_pose(x, y, z + d / 2, rod[1]), size=Vector3(x=rod[0], y=d, z=d),
                                              color=col)]}
    return text, {"spheres": [SpherePrimitive(pose=_pose(x, y, z + d / 2), size=Vector3(x=d, y=d, z=d), color=col)]}


def believed(checkpoint: dict) -> tuple[list[dict], list]:
    """A checkpoint's believed objects, the lost left out, and the ids of the lost (sorted)."""
    belief = checkpoint.get("belief") or {}
    lost = set(belief.get("lost", ()))
    return [o for o in belief.get("objects", ()) if o.get("id") not in lost], sorted(lost)


def paths_scene(paths, colour, stamp, thickness: float = 2.0, clear: bool = False):
    """Tip paths ``(entity id, points)`` as line strips; ``clear``: first delete every
    path the topic drew before (a replan's paths replace the last plan's)."""
    from foxglove.messages import (Color, LinePrimitive, LinePrimitiveLineType, SceneEntityDeletion,
                                   SceneEntityDeletionType, SceneUpdate)

    col = Color(r=colour[0], g=colour[1], b=colour[2], a=colour[3])
    entities = []
    for ident, pts in paths:
        pts = [p for p in pts if len(p) >= 2]
        if len(pts) < 2:
            continue
        line = LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=_pose(0.0, 0.0, 0.0),
                             thickness=thickness, scale_invariant=True,
                             points=[_point(p[0], p[1], 1.0) for p in pts], color=col)
        entities.append(_entity(ident, stamp, lines=[line]))
    deletions = ([SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)] if clear else [])
    return SceneUpdate(entities=entities, deletions=deletions)


def layout_scene(layout, registration: dict | None = None):
    """Slots as outlines (circles, capsules), keep-outs, and the working area (at time 0);
    with ``registration`` (a plan's, as a dict), the layout mapped into the scan's frame,
    where the run works once its marks were registered."""
    from foxglove.messages import Color, LinePrimitive, LinePrimitiveLineType, SceneUpdate, TextPrimitive

    if registration is not None and layout.registration is None:
        from nanoasm.cad.frame import similarity_from_table
        from nanoasm.schema import Table

        layout = layout.mapped(similarity_from_table(Table(registration, "plan")), layout.area)

    def loop(pts, colour):
        return LinePrimitive(type=LinePrimitiveLineType.LineLoop, pose=_pose(0.0, 0.0, 0.0), thickness=2.0,
                             scale_invariant=True, points=[_point(x, y, 0.0) for x, y in pts],
                             color=Color(r=colour[0], g=colour[1], b=colour[2], a=colour[3]))

    target = COLOURS["target"]
    w, h = layout.area
    entities = [_entity("area", timestamp(0), lines=[loop([(0, 0), (w, 0), (w, h), (0, h)], COLOURS["area"])])]
    for tg in layout.targets:
        ring = tg.geometry().buffer(tg.radius, quad_segs=12).exterior.coords[:-1]
        label = TextPrimitive(pose=_pose(tg.at[0], tg.at[1], 0.0), billboard=True, font_size=12.0,
                              scale_invariant=True, text=tg.id,
                              color=Color(r=target[0], g=target[1], b=target[2], a=1.0))
        entities.append(_entity(f"slot:{tg.id}", timestamp(0), lines=[loop(ring, target)], texts=[label]))
    for i, k in enumerate(layout.keepouts, 1):
        entities.append(_entity(f"keepout:{i}", timestamp(0), lines=[loop(k.polygon, COLOURS["keepout"])]))
    for i, k in enumerate(layout.marks, 1):       # alignment marks: keep-outs too
        entities.append(_entity(f"mark:{i}", timestamp(0), lines=[loop(k.polygon, COLOURS["keepout"])]))
    return SceneUpdate(entities=entities)


def scan_line_scene(doc: dict, stamp):
    """A local scan line (a ``scan_line`` document) where it lay on the sample, the offset
    it was shifted by taken out; None for a line without one."""
    off = doc.get("offset")
    if off is None:
        return None
    a = np.asarray(doc["a"], float) - np.asarray(off, float)
    b = np.asarray(doc["b"], float) - np.asarray(off, float)
    return paths_scene([("line", (a.tolist(), b.tolist()))], COLOURS["scan"], stamp, thickness=4.0)


def _entity(ident: str, stamp, **primitives):
    from foxglove.messages import SceneEntity

    return SceneEntity(timestamp=stamp, frame_id="layout", id=ident, **primitives)


def _point(x: float, y: float, z: float):
    from foxglove.messages import Point3

    return Point3(x=float(x), y=float(y), z=float(z))


def _pose(x: float, y: float, z: float, angle_deg: float = 0.0):
    """A pose at (x, y, z) turned by ``angle_deg`` about +z."""
    from foxglove.messages import Pose, Quaternion, Vector3

    half = math.radians(angle_deg) / 2
    return Pose(position=Vector3(x=float(x), y=float(y), z=float(z)),
                orientation=Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)))
