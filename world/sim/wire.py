"""A flexible wire (aspect ratio σ > 25) as a chain of segments that bends where pushed.

The seed observes that wires with σ > 25 bend rather than turn (Fig. 4.7) and, for DNA
(ch. 6, Fig. 6.3), models a push as a deformation confined to an *affecting region* of
radius ``a`` around the push point, drawn as a 4th-order polynomial that meets the
undeformed wire with matching slopes at both ends of the region. Here:

- the wire is a polyline of ``m + 1`` nodes (``m`` capsule segments of equal length);
- the contact point follows the tip (it is put back at the contact distance from the tip,
  as :func:`~nanoasm.world.particle_push.particle_step` does for a particle);
- the other nodes follow with the displacement scaled by the quartic bump
  ``w(s) = (1 - (s/a)²)²`` of their arc distance ``s`` to the contact point: 1 at the
  contact, 0 with zero slope at the edge of the affecting region, the smooth join of the
  seed's polynomial;
- the segment lengths are then restored outwards from the node nearest the contact, so
  the wire never stretches: parts beyond the region are dragged, never rotated rigidly.

Lengths in nm, positions ``(m + 1, 2)`` arrays.
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.bodies import Body

#: Segments per wire: about one per two diameters, within these bounds.
MIN_SEGMENTS, MAX_SEGMENTS = 6, 48


def segment_count(length: float, diameter: float) -> int:
    """Number of segments of a wire of ``length`` and ``diameter`` (nm)."""
    return int(min(MAX_SEGMENTS, max(MIN_SEGMENTS, round(length / diameter / 2.0))))


def affect_radius(length: float, diameter: float, fraction: float = 0.25, min_diameters: float = 4.0) -> float:
    """Radius ``a`` (nm) of the region a push deforms (seed ch. 6, Fig. 6.3): ``fraction``
    of the length, at least ``min_diameters`` diameters (``[sim] wire_affect_*``; the
    seed's a = f(b, t) is empirical)."""
    return min(length, max(min_diameters * diameter, fraction * length))


def initial_nodes(body: Body, m: int) -> np.ndarray:
    """``(m + 1, 2)`` nodes evenly along a straight wire's core."""
    a, b = body.core()
    f = np.linspace(0.0, 1.0, m + 1)[:, None]
    return np.asarray(a, float) + f * (np.asarray(b, float) - np.asarray(a, float))


def closest_point(nodes: np.ndarray, p: tuple[float, float]) -> tuple[int, float, float]:
    """``(k, f, distance)``: the point of the polyline nearest ``p`` lies on segment ``k``
    at fraction ``f`` (0 at node ``k``, 1 at node ``k + 1``)."""
    a, d = nodes[:-1], np.diff(nodes, axis=0)
    n2 = np.einsum("ij,ij->i", d, d)
    rel = np.asarray(p, float) - a
    f = np.clip(np.einsum("ij,ij->i", rel, d) / np.where(n2 > 0, n2, 1.0), 0.0, 1.0)
    gap = rel - f[:, None] * d
    dist = np.hypot(gap[:, 0], gap[:, 1])
    k = int(np.argmin(dist))
    return k, float(f[k]), float(dist[k])


def bend(nodes: np.ndarray, k: int, f: float, delta: tuple[float, float], radius: float) -> np.ndarray:
    """Nodes after the point at ``(k, f)`` moves by ``delta`` (nm), deforming within ``radius``.

    Returns a new ``(m + 1, 2)`` array whose segment lengths equal the old ones.
    """
    seg = np.hypot(*np.diff(nodes, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s_c = s[k] + f * seg[k]
    x = np.clip(np.abs(s - s_c) / radius, 0.0, 1.0)
    w = (1.0 - x * x) ** 2
    w_c = max((1.0 - f) * w[k] + f * w[k + 1], 1e-6)
    out = nodes + (w / w_c)[:, None] * np.asarray(delta, float)
    anchor = k if f <= 0.5 else k + 1
    for j in range(anchor + 1, len(out)):
        out[j] = _at_length(out[j - 1], out[j], seg[j - 1], nodes[j] - nodes[j - 1])
    for j in range(anchor - 1, -1, -1):
        out[j] = _at_length(out[j + 1], out[j], seg[j], nodes[j] - nodes[j + 1])
    return out


def _at_length(fixed: np.ndarray, free: np.ndarray, length: float, fallback: np.ndarray) -> np.ndarray:
    v = free - fixed
    n = math.hypot(v[0], v[1])
    if n <= 1e-12 * max(1.0, length):
        v, n = fallback, math.hypot(fallback[0], fallback[1])
    return fixed + v * (length / n)


def segment_bodies(wire_id: str, nodes: np.ndarray, diameter: float) -> list[Body]:
    """One capsule per segment (kind ``"rod"``) whose core runs between its two nodes."""
    out = []
    for j in range(len(nodes) - 1):
        out.append(segment_body(f"{wire_id}#{j}", nodes[j], nodes[j + 1], diameter))
    return out


def segment_body(unit_id: str, p: np.ndarray, q: np.ndarray, diameter: float) -> Body:
    """A capsule of ``diameter`` whose core is the segment ``p``-``q``."""
    dx, dy = float(q[0] - p[0]), float(q[1] - p[1])
    core = math.hypot(dx, dy)
    angle = math.degrees(math.atan2(dy, dx)) if core > 0 else 0.0
    mid = (float(p[0] + q[0]) / 2, float(p[1] + q[1]) / 2)
    return Body(unit_id, "rod", mid, diameter, angle, core + diameter)


def chord_body(wire_id: str, nodes: np.ndarray, diameter: float) -> Body:
    """The wire reported as a rod: the capsule on its end-to-end chord."""
    return segment_body(wire_id, nodes[0], nodes[-1], diameter)


def sync_nodes(nodes: np.ndarray, cores_a: np.ndarray, cores_b: np.ndarray) -> np.ndarray:
    """Nodes after the segments were shoved (translated) one by one by contacts.

    Segment ``j``'s core now runs ``cores_a[j]``-``cores_b[j]``; each node takes the
    larger of the displacements its one or two segments gave it, so a shoved segment
    moves fully and drags its neighbours' shared ends (a local bend).
    """
    da = cores_a - nodes[:-1]
    db = cores_b - nodes[1:]
    disp = np.zeros_like(nodes)
    disp[:-1] = da
    take = np.hypot(*db.T) > np.hypot(*disp[1:].T)
    disp[1:][take] = db[take]
    return nodes + disp
