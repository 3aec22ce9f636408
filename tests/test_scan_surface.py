"""The full scan as a 3-D surface (``/scan/surface``): the mesh of known height maps read
back from its glb with trimesh, downsampling, holes where heights are missing, objects
resting on the surface, and a logged dry-run's surface message."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from runlogkit import logged_dry_run

from nanoasm.executor.documents import CHECKPOINT, ENVIRONMENT, FULL_SCAN
from nanoasm.executor.foxglove_scenes import timestamp
from nanoasm.executor.logread import read_log
from nanoasm.executor.scan_surface import (HEIGHT_EXAGGERATION, MAX_SIDE, SURFACE_TOPIC, SurfaceView, glb_bytes,
                                           surface_grid, surface_mesh, surface_scene)

K = HEIGHT_EXAGGERATION


def from_glb(data: bytes) -> trimesh.Trimesh:
    """The one mesh of a glb, as trimesh loads it."""
    scene = trimesh.load(io.BytesIO(data), file_type="glb")
    (mesh,) = scene.geometry.values()
    return mesh


def decoded(msg):
    """A Foxglove message as the log's reader decodes it (protobuf, fields readable); bytes
    are an encoded ``foxglove.SceneUpdate`` (:func:`~nanoasm.executor.foxglove_scenes.bodies_scene`)."""
    from foxglove.messages import SceneUpdate
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    s = SceneUpdate.get_schema() if isinstance(msg, bytes) else msg.get_schema()
    return DecoderFactory().decoder_for("protobuf", Schema(id=1, name=s.name, encoding=s.encoding, data=s.data))(
        msg if isinstance(msg, bytes) else msg.encode())


def ramp(ny: int, nx: int) -> np.ndarray:
    """Heights 0.1 * (i + 2 j) nm at row i, column j (multiples of the rounding step)."""
    i, j = np.mgrid[0:ny, 0:nx]
    return 0.1 * (i + 2 * j)


def test_a_known_height_map_meshes_to_its_extent_with_exaggerated_heights():
    h = ramp(30, 40)
    mesh = from_glb(glb_bytes(surface_mesh(surface_grid(h, 10.0, (100.0, 200.0)))))
    assert len(mesh.vertices) == 30 * 40 and len(mesh.faces) == 2 * 29 * 39
    # pixel centres: x 105 .. 495, y 205 .. 495; heights x K, from 0 to 0.1 * (29 + 78)
    assert mesh.bounds == pytest.approx(np.array([[105.0, 205.0, 0.0], [495.0, 495.0, K * 10.7]]), abs=1e-3)
    at = {(round(x), round(y)): z for x, y, z in mesh.vertices}
    assert at[(105 + 10 * 7, 205 + 10 * 3)] == pytest.approx(K * 0.1 * (3 + 2 * 7), abs=1e-4)
    assert np.all(mesh.face_normals[:, 2] > 0), "the surface faces up"
    colours = np.asarray(mesh.visual.vertex_attributes["color"])      # dark at the lowest, white at the highest
    assert colours.shape == (30 * 40, 4)
    low, high = colours[np.argmin(mesh.vertices[:, 2])], colours[np.argmax(mesh.vertices[:, 2])]
    assert tuple(low) == (102, 0, 0, 255) and tuple(high) == (255, 255, 255, 255)


def test_a_large_scan_is_downsampled_to_block_means_at_block_centres():
    h = ramp(520, 600)                     # f = ceil(600 / 256) = 3: 174 x 200 vertices, the last row of one pixel
    s = surface_grid(h, 2.0)
    assert s.z.shape == (174, 200) and max(s.z.shape) <= MAX_SIDE
    assert s.x[0] == pytest.approx(3.0) and s.y[-1] == pytest.approx(2.0 * 519.5)
    assert s.z[1, 2] == pytest.approx(K * h[3:6, 6:9].mean()) and s.z[-1, 0] == pytest.approx(K * h[519, 0:3].mean())
    mesh = from_glb(glb_bytes(surface_mesh(s)))
    assert len(mesh.vertices) == 174 * 200
    assert mesh.bounds[:, :2] == pytest.approx(np.array([[3.0, 3.0], [1197.0, 1039.0]]))


def test_missing_heights_leave_holes_and_a_scan_without_any_is_refused():
    h = ramp(6, 5)
    h[2, 3] = np.nan
    mesh = surface_mesh(surface_grid(h, 1.0))
    # the four cells at the hole go, and with them the vertex at the border beside it (in no other cell)
    assert len(mesh.faces) == 2 * (4 * 5 - 4) and len(mesh.vertices) == 6 * 5 - 2
    assert np.isfinite(mesh.vertices).all()
    with pytest.raises(ValueError, match="no cell"):
        surface_mesh(surface_grid(np.full((4, 4), np.nan), 1.0))
    with pytest.raises(ValueError, match="pixel_size"):
        surface_grid(h, 0.0)


@settings(max_examples=40, deadline=None)
@given(arrays(float, st.tuples(st.integers(2, 12), st.integers(2, 12)),
              elements=st.one_of(st.floats(-50, 50), st.just(np.nan))))
def test_a_mesh_holds_every_cell_of_four_finite_heights_and_no_nan(h):
    s = surface_grid(h, 3.0)
    cells = int((np.isfinite(s.z[:-1, :-1]) & np.isfinite(s.z[1:, :-1]) & np.isfinite(s.z[:-1, 1:])
                 & np.isfinite(s.z[1:, 1:])).sum())
    if cells == 0:
        with pytest.raises(ValueError):
            surface_mesh(s)
        return
    mesh = surface_mesh(s)
    assert len(mesh.faces) == 2 * cells and np.isfinite(mesh.vertices).all()
    assert mesh.faces.max() < len(mesh.vertices) and len(np.unique(mesh.faces)) == len(mesh.vertices)


def test_objects_rest_on_the_highest_surface_under_them():
    h = np.zeros((50, 50))
    h[20:23, 30:33] = 40.0                 # a bump at x, y in [30, 33) x [20, 23) (pixel 1 nm)
    s = surface_grid(h, 1.0)
    assert s.rest({"id": "p", "at": [31.5, 21.5], "diameter": 4.0}) == pytest.approx(K * 40.0)
    assert s.rest({"id": "p", "at": [10.0, 10.0], "diameter": 4.0}) == 0.0
    assert s.rest({"id": "p", "at": [500.0, 10.0], "diameter": 4.0}) == 0.0            # off the scan
    rod = {"id": "r", "at": [21.5, 21.5], "diameter": 2.0, "length": 16.0, "angle": 0.0}
    assert s.rest(rod) == pytest.approx(K * 40.0)                 # its end reaches the bump
    assert s.rest({**rod, "angle": 90.0}) == 0.0
    (entity,) = decoded(surface_scene(s, timestamp(0))).entities
    assert entity.frame_id == "layout" and {m.key: m.value for m in entity.metadata}["height_exaggeration"] == f"{K:g}"


def test_a_scan_that_cannot_be_meshed_is_a_warning_not_a_failed_run():
    logged = []
    view = SurfaceView(lambda topic, msg, t: logged.append((topic, msg)), lambda t: timestamp(0))
    view(FULL_SCAN, {"t": 1.0, "height": np.full((4, 4), np.nan), "pixel_size": 1.0, "origin": [0, 0]}, 1.0)
    assert [t for t, _ in logged] == ["/events"] and "no /scan/surface" in decoded(logged[0][1]).message
    view(ENVIRONMENT, {"objects": [{"id": "p1", "at": [1, 1], "diameter": 2.0}]}, 2.0)
    assert logged[-1][0] == SURFACE_TOPIC and decoded(logged[-1][1]).entities[0].spheres[0].pose.position.z == 1.0


def test_a_dry_run_logs_the_surface_with_the_objects_on_it(tmp_path):
    path = tmp_path / "run.mcap"
    _, rec = logged_dry_run(path)
    log = read_log(path)
    msgs = log.topic(SURFACE_TOPIC)
    assert msgs and all(m.schema == "foxglove.SceneUpdate" for m in msgs)
    (surface,) = msgs[0].data.entities
    (model,) = surface.models
    assert surface.id == "surface" and surface.frame_id == "layout" and model.media_type == "model/gltf-binary"
    mesh = from_glb(model.data)
    grid = log.last("/scan").data
    heights = np.frombuffer(grid.data, "<f4")
    side = grid.column_count * grid.cell_size.x                                   # 5000 nm, 500 pixels
    assert len(mesh.vertices) == 250 * 250
    assert mesh.bounds[:, :2] == pytest.approx(np.array([[10.0, 10.0], [side - 10.0, side - 10.0]]))
    assert 0.8 * K * heights.max() < mesh.bounds[1, 2] <= K * heights.max() + 1.0  # 2 x 2 means of the peaks
    # the identified objects, then the belief after every push, rest on the surface
    objects = msgs[1].data.entities
    assert len(objects) == len(rec.topic(ENVIRONMENT)[0]["objects"])
    assert all((e.spheres or e.cubes)[0].pose.position.z > K * 20 for e in objects)   # each on its own bump
    assert len(msgs) == 2 + len(rec.topic(CHECKPOINT))
