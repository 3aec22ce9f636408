"""The full scan as a 3-D surface in Foxglove's 3-D panel: the dissertation's
augmented-reality view, rebuilt from the run log (channel :data:`SURFACE_TOPIC`).

The height map is block-averaged down to at most :data:`MAX_SIDE` vertices a side,
meshed with trimesh (two triangles per grid cell, coloured by height), and embedded as
binary glTF in a ``foxglove.SceneUpdate`` (one ``ModelPrimitive``). Heights are
exaggerated by :data:`HEIGHT_EXAGGERATION` so that objects tens of nm high stand out on
a scan some µm wide; x and y are nm in the layout frame, as on ``/scan``. Pixels with no
height (NaN) leave a hole: a cell with one is not drawn.

The objects are drawn on it at true size, each resting on the highest point of the
(exaggerated) surface under it: the identified ones first, then the executor's belief
after every push and its local scans. Local scans are logged as single lines
(``/local_scan``: end points and heights), not as areas, so the surface itself stays the
full scan's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .documents import CHECKPOINT, ENVIRONMENT, FULL_SCAN
from .foxglove_scenes import COLOURS, believed, bodies_scene, log_line

#: The channel of the surface and the objects on it.
SURFACE_TOPIC = "/scan/surface"
#: Factor the surface's heights are drawn with (x and y are drawn at 1:1).
HEIGHT_EXAGGERATION = 5.0
#: Most vertices along either side of the mesh (a 500 x 500 scan is meshed at 250 x 250).
MAX_SIDE = 256
#: Heights are rounded to this step (nm) before they are exaggerated: below an AFM's
#: noise, and the bowtie's mesh compresses to 638 kB instead of 837 kB.
HEIGHT_STEP = 0.1
#: Resting heights kept at most (then forgotten at once and found again as asked for).
REST_KEPT = 100_000
#: What the channel holds (the log's channel table and docs/logs.md say the same).
DESCRIPTION = (f"the full scan as a 3-D surface (glTF model; heights x{HEIGHT_EXAGGERATION:g}), "
               "with the objects on it, identified then believed after each push")


@dataclass(frozen=True)
class Surface:
    """A height map on a grid of vertices: ``x`` (nx,) and ``y`` (ny,) in nm, layout
    frame; ``z`` (ny, nx) in nm times ``exaggeration``, NaN where there is no height."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    exaggeration: float

    def rest(self, body: dict) -> float:
        """The highest surface point (exaggerated, nm) within a body's footprint: a disc
        of its diameter, or a rod's or wire's capsule; 0 off the surface."""
        try:
            x, y = (float(v) for v in body["at"])
            d = float(body["diameter"])
            half = 0.5 * float(body.get("length") or 0.0)
            angle = math.radians(float(body.get("angle") or 0.0))
        except (KeyError, TypeError, ValueError):
            return 0.0
        reach = 0.5 * d + 0.5 * max(_step(self.x), _step(self.y))    # at least the nearest vertex
        ux, uy = math.cos(angle), math.sin(angle)
        cols = np.flatnonzero(np.abs(self.x - x) <= half + reach)
        rows = np.flatnonzero(np.abs(self.y - y) <= half + reach)
        dx, dy = self.x[cols][None, :] - x, self.y[rows][:, None] - y
        along = np.clip(dx * ux + dy * uy, -half, half)
        inside = np.hypot(dx - along * ux, dy - along * uy) <= reach
        z = self.z[np.ix_(rows, cols)][inside]
        z = z[np.isfinite(z)]
        return float(z.max()) if z.size else 0.0


def _step(v: np.ndarray) -> float:
    return float(np.max(np.diff(v))) if len(v) > 1 else 0.0


def surface_grid(height, pixel_size: float, origin=(0.0, 0.0), *, max_side: int = MAX_SIDE,
                 exaggeration: float = HEIGHT_EXAGGERATION) -> Surface:
    """A scan's heights (``(ny, nx)``, row 0 at the bottom; pixel (i, j) centred at
    ``origin + (j + 0.5, i + 0.5) * pixel_size``) averaged over blocks of ``f x f``
    pixels, ``f`` the least that leaves at most ``max_side`` vertices a side; each vertex
    at the centre of its block's pixels, NaN where the block has no finite height."""
    h = np.asarray(height, float)
    if h.ndim != 2 or min(h.shape) < 2:
        raise ValueError(f"height must be a 2-D array of at least 2 x 2, got shape {h.shape}")
    if not (math.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    if max_side < 2:
        raise ValueError(f"max_side must be at least 2, got {max_side}")
    if not (math.isfinite(exaggeration) and exaggeration > 0):
        raise ValueError(f"exaggeration must be positive and finite, got {exaggeration}")
    ny, nx = h.shape
    f = max(1, math.ceil(max(ny, nx) / max_side))
    starts = np.arange(0, nx, f)
    mean = np.full((-(-ny // f), len(starts)), np.nan)
    for i, row in enumerate(range(0, ny, f)):               # a band of f rows at a time: no copy of h
        band = h[row:row + f]
        finite = np.isfinite(band)
        count = np.add.reduceat(finite.sum(axis=0), starts)
        total = np.add.reduceat(np.where(finite, band, 0.0).sum(axis=0), starts)
        np.divide(total, count, out=mean[i], where=count > 0)
    z = np.round(mean / HEIGHT_STEP) * HEIGHT_STEP * exaggeration
    ox, oy = (float(v) for v in origin)
    return Surface(_centres(nx, f, ox, pixel_size), _centres(ny, f, oy, pixel_size), z, float(exaggeration))


def _centres(n: int, f: int, start: float, pixel_size: float) -> np.ndarray:
    """Centres of the blocks of ``f`` pixels along an axis of ``n`` (the last may be short)."""
    lo = np.arange(0, n, f)
    return start + pixel_size * (lo + np.minimum(lo + f, n)) / 2


def surface_mesh(surface: Surface):
    """The surface as a ``trimesh.Trimesh``: a vertex per finite grid point, two
    triangles (facing +z) per grid cell whose four corners are finite, vertex colours by
    height, a matte two-sided material. ValueError when no cell is finite."""
    import trimesh
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    ny, nx = surface.z.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    z = surface.z.ravel()
    ok = (np.isfinite(z[a]) & np.isfinite(z[b]) & np.isfinite(z[c]) & np.isfinite(z[d])).ravel()
    if not ok.any():
        raise ValueError("the scan has no cell of four finite heights")
    quads = np.column_stack([a.ravel(), b.ravel(), c.ravel(), d.ravel()])[ok]
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    used = np.zeros(z.size, bool)                 # drop the vertices no face uses (NaN ones)
    used[faces] = True
    xx, yy = np.meshgrid(surface.x, surface.y)
    vertices = np.column_stack([xx.ravel()[used], yy.ravel()[used], z[used]])
    faces = (np.cumsum(used) - 1)[faces]
    visual = TextureVisuals(material=PBRMaterial(name="scan", metallicFactor=0.0, roughnessFactor=1.0,
                                                 doubleSided=True))
    visual.vertex_attributes["color"] = height_colours(vertices[:, 2])
    return trimesh.Trimesh(vertices, faces, visual=visual, process=False)


def height_colours(z: np.ndarray) -> np.ndarray:
    """RGBA bytes (n, 4) for heights ``z``: an AFM palette (afmhot, from dark brown at
    the lowest through orange to white at the highest)."""
    lo, hi = float(np.min(z)), float(np.max(z))
    s = 0.2 + 0.8 * ((z - lo) / (hi - lo) if hi > lo else np.zeros_like(z))
    rgb = np.clip(np.column_stack([2 * s, 2 * s - 0.5, 2 * s - 1.0]), 0.0, 1.0)
    return np.column_stack([np.round(255 * rgb), np.full(len(z), 255)]).astype(np.uint8)


def glb_bytes(mesh) -> bytes:
    """A mesh as binary glTF (no normals: viewers shade it flat)."""
    return mesh.export(file_type="glb", include_normals=False)


def surface_scene(surface: Surface, stamp):
    """A ``foxglove.SceneUpdate`` of entity ``surface``: the mesh as an embedded
    ``model/gltf-binary`` model in the layout frame, a note of the height factor at the
    lower-left corner, and the factor in the entity's metadata."""
    from foxglove.messages import (Color, KeyValuePair, ModelPrimitive, Pose, Quaternion, SceneEntity,
                                   SceneUpdate, TextPrimitive, Vector3)

    at = Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(w=1.0))
    model = ModelPrimitive(pose=at, scale=Vector3(x=1.0, y=1.0, z=1.0), override_color=False,
                           media_type="model/gltf-binary", data=glb_bytes(surface_mesh(surface)))
    factor = f"{surface.exaggeration:g}"
    note = TextPrimitive(pose=Pose(position=Vector3(x=float(surface.x[0]), y=float(surface.y[0]), z=0.0),
                                   orientation=Quaternion(w=1.0)),
                         billboard=True, font_size=12.0, scale_invariant=True, color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                         text=f"full scan, heights x{factor}")
    entity = SceneEntity(timestamp=stamp, frame_id="layout", id="surface", models=[model], texts=[note],
                         metadata=[KeyValuePair(key="height_exaggeration", value=factor),
                                   KeyValuePair(key="units", value="nm")])
    return SceneUpdate(entities=[entity])


class SurfaceView:
    """The run log's :data:`SURFACE_TOPIC`: told every document the log records, it logs
    the surface at the full scan, the identified objects resting on it, and after every
    checkpoint the believed ones (the lost removed). ``log(topic, message, t)`` and
    ``stamp(t)`` are the run log's. A scan that cannot be meshed is a warning on
    ``/events``, never a failed run."""

    def __init__(self, log: Callable[[str, Any, float | None], None], stamp: Callable[[float | None], Any]):
        self._log, self._stamp = log, stamp
        self.surface: Surface | None = None
        self._rests: dict[tuple, float] = {}
        self._drawn: dict = {}          # bodies_scene's memo of the checkpoints' bodies on this surface

    def _rest(self, body: dict) -> float:
        """:meth:`Surface.rest`, kept by the body's pose and size: a checkpoint redraws every
        object, and between two of them most have not moved (a 1000-object run: 520
        redraws of 1000, 34 s of its compute when each was found again)."""
        key = tuple(repr(body.get(k)) for k in ("at", "diameter", "length", "angle"))
        z = self._rests.get(key)
        if z is None:
            if len(self._rests) >= REST_KEPT:
                self._rests.clear()
            z = self._rests[key] = self.surface.rest(body)
        return z

    def __call__(self, topic: str, doc: dict, t: float | None) -> None:
        if topic == FULL_SCAN:
            self._on_full_scan(doc, t)
        elif topic == ENVIRONMENT:
            self._draw(doc.get("objects", ()), (), COLOURS["object"], t)
        elif topic == CHECKPOINT:
            self._draw(*believed(doc), COLOURS["belief"], t, self._drawn)

    def _on_full_scan(self, doc: dict, t: float | None) -> None:
        try:
            surface = surface_grid(doc["height"], float(doc["pixel_size"]), doc.get("origin", (0.0, 0.0)))
            msg = surface_scene(surface, self._stamp(t))
        except Exception as err:  # noqa: BLE001 - a view of the log must not stop a run
            self._log("/events", log_line(self._stamp(t), "warning", f"no {SURFACE_TOPIC}: {err}"), t)
            return
        self.surface = surface
        self._rests.clear()
        self._drawn.clear()
        self._log(SURFACE_TOPIC, msg, t)

    def _draw(self, bodies, lost, colour, t: float | None, memo: dict | None = None) -> None:
        rest = self._rest if self.surface is not None else None
        self._log(SURFACE_TOPIC, bodies_scene(bodies, "obj", colour, self._stamp(t), delete=lost, lift=rest, memo=memo),
                  t)
