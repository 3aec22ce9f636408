"""Relocalisation by registration: windows chosen in a rendered full scan
(executor/windows.py), and new small scans of them registered back at known shifts
(executor/registration.py). Scenes are rendered by world.render: electrodes 30 nm high,
a cluster of 20 nm particles, 10 nm pixels, 0.3 nm noise, 0.2 nm roughness; windows of
48 pixels (480 nm)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely

from nanoasm.bodies import Body
from nanoasm.executor.registration import Registration, register
from nanoasm.executor.windows import Window, choose_windows
from nanoasm.instrument import HeightImage
from nanoasm.world.render import make_surface, render_scan

PIXEL = 10.0
SIZE = 480.0
AREA = (2560.0, 2560.0)
BOX = shapely.box(300.0, 300.0, 1100.0, 900.0)
SLANT = shapely.Polygon([(1500.0, 1600.0), (2300.0, 1500.0), (2200.0, 2200.0), (1600.0, 2100.0)])
CLUSTER = [(1700.0, 500.0), (1760.0, 530.0), (1720.0, 600.0), (1850.0, 450.0), (1800.0, 650.0)]
PARTICLES = [Body(f"p{i}", "particle", xy, 20.0) for i, xy in enumerate(CLUSTER)]
CORNERS = [(300.0, 300.0), (1100.0, 300.0), (300.0, 900.0), (1100.0, 900.0), *SLANT.exterior.coords[:-1]]


def centred(x, y) -> tuple[float, float]:
    """Lower-left corner of the window of side SIZE centred at (x, y), on the pixel grid."""
    return round((x - SIZE / 2) / PIXEL) * PIXEL, round((y - SIZE / 2) / PIXEL) * PIXEL


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(3)
    surface = make_surface(PARTICLES, [(BOX, 30.0), (SLANT, 30.0)], AREA, rng=rng)
    return surface, render_scan(surface, PIXEL, rng=rng)


def new_scan(surface, corner, shift, rng) -> HeightImage:
    """A new scan whose content lies ``shift`` from where the reference shows it: the
    caller believes it covers the window at ``corner``."""
    x0, y0 = corner
    image = render_scan(surface, PIXEL, window=(x0 - shift[0], y0 - shift[1], SIZE, SIZE), rng=rng)
    return HeightImage(image.height, PIXEL, (x0, y0))


def crop(image: HeightImage, corner) -> HeightImage:
    j, i = (int(round((c - o) / PIXEL)) for c, o in zip(corner, image.origin))
    k = int(SIZE / PIXEL)
    return HeightImage(image.height[i:i + k, j:j + k], PIXEL, corner)


def window_score(image, corner) -> float:
    return choose_windows(crop(image, corner), SIZE, count=1)[0].score


# ---------------------------------------------------------------- windows

def test_windows_prefer_corners_and_clusters(world):
    _, image = world
    windows = choose_windows(image, SIZE, count=4)
    assert len(windows) == 4 and all(isinstance(w, Window) for w in windows)
    assert [w.score for w in windows] == sorted((w.score for w in windows), reverse=True)
    marks = np.array(CORNERS + [np.mean(CLUSTER, axis=0)])
    for w in windows:
        x0, y0, x1, y1 = w.region
        assert x1 - x0 == SIZE and y1 - y0 == SIZE
        centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
        assert np.min(np.hypot(*(marks - centre).T)) < 0.3 * SIZE, w
    corner = window_score(image, centred(1100.0, 900.0))
    cluster = window_score(image, centred(1760.0, 550.0))
    edge = window_score(image, centred(700.0, 900.0))        # the middle of a straight side
    bare = window_score(image, centred(2200.0, 900.0))
    assert min(corner, cluster) > 10 * max(edge, bare), (corner, cluster, edge, bare)


def test_windows_respect_avoid(world):
    _, image = world
    # with the electrodes masked, the cluster is the one distinctive place left
    avoid = shapely.union(BOX, SLANT)
    windows = choose_windows(image, SIZE, count=3, avoid=avoid)
    assert shapely.box(*windows[0].region).contains(shapely.MultiPoint(CLUSTER).centroid)
    for w in windows:
        box = shapely.box(*w.region)
        assert box.intersection(avoid.buffer(20.0)).area <= 0.5 * box.area
    assert windows[0].score < choose_windows(image, SIZE, count=1)[0].score
    everything = shapely.box(0.0, 0.0, *AREA)
    assert choose_windows(image, SIZE, avoid=everything) == ()
    with pytest.raises(ValueError, match="size"):
        choose_windows(image, 50.0)
    with pytest.raises(ValueError, match="avoid"):
        choose_windows(image, SIZE, avoid=[(0, 0)])


# ---------------------------------------------------------------- registration

def test_register_recovers_random_shifts(world):
    """Shifts up to 40 % of the side in each axis, sub-pixel, on a window centred on an
    electrode's corner and on one centred on the cluster, 60 each. Measured over seeds
    0-7: all 60 ok for both; within 2 std in both axes 100 % (corner) and 92-100 %
    (cluster); rms error over rms std 0.67-0.76 and 0.51-0.68."""
    surface, image = world
    rng = np.random.default_rng(7)
    inside = []
    for centre in ((1100.0, 900.0), (1760.0, 550.0)):
        corner = centred(*centre)
        errors, stds = [], []
        for _ in range(60):
            shift = rng.uniform(-0.4, 0.4, 2) * SIZE
            result = register(image, new_scan(surface, corner, shift, rng))
            assert isinstance(result, Registration)
            if result.ok:
                errors.append(result.shift - shift)
                stds.append(result.std)
                assert 0.9 < result.score <= 1.0
        errors, stds = np.array(errors), np.array(stds)
        assert len(errors) >= 54
        assert 0.3 < np.sqrt(np.mean(errors ** 2)) / np.sqrt(np.mean(stds ** 2)) < 1.2
        assert np.abs(errors).max() < 3.0
        inside += list(np.all(np.abs(errors) <= 2 * stds[:, None], axis=1))
    assert np.mean(inside) >= 0.95


def test_register_refuses_poor_and_ambiguous_matches(world):
    surface, image = world
    rng = np.random.default_rng(9)
    bare = register(image, new_scan(surface, centred(2200.0, 900.0), (20.0, -30.0), rng))
    assert not bare.ok and bare.reason.startswith("poor match")
    # the cluster scanned, but believed to be at the box's corner
    elsewhere = new_scan(surface, centred(1760.0, 550.0), (0.0, 0.0), rng)
    wrong = register(image, HeightImage(elsewhere.height, PIXEL, centred(1100.0, 900.0)))
    assert not wrong.ok and wrong.reason.startswith("poor match")
    edge = register(image, new_scan(surface, centred(700.0, 900.0), (35.0, 12.0), rng))
    assert not edge.ok and edge.reason.startswith("ambiguous")
    # beyond max_shift: the masked correlation still sees it on the part that overlaps
    far = register(image, new_scan(surface, centred(1100.0, 900.0), (150.0, 0.0), rng), max_shift=60.0)
    assert not far.ok and far.reason.startswith("shift at or beyond the search limit of 60 nm")


def test_register_with_masks_of_a_moved_particle(world):
    surface, image = world
    rng = np.random.default_rng(5)
    moved = list(PARTICLES)
    moved[2] = Body("p2", "particle", (1660.0, 640.0), 20.0)   # pushed 70 nm since
    after = make_surface(moved, [(BOX, 30.0), (SLANT, 30.0)], AREA, rng=np.random.default_rng(3))
    corner = centred(1760.0, 550.0)
    errors, stds = [], []
    for _ in range(20):
        shift = rng.uniform(-0.3, 0.3, 2) * SIZE
        scan = new_scan(after, corner, shift, rng)
        x, y = image.pixel_centres()
        ref_mask = shapely.contains_xy(shapely.Point(CLUSTER[2]).buffer(40.0), x[None, :], y[:, None])
        mx, my = scan.pixel_centres()
        new_at = shapely.Point(1660.0 + shift[0], 640.0 + shift[1]).buffer(60.0)
        result = register(image, scan, reference_mask=~ref_mask,
                          moving_mask=~shapely.contains_xy(new_at, mx[None, :], my[:, None]))
        assert result.ok, result.reason
        errors.append(result.shift - shift)
        stds.append(result.std)
    errors, stds = np.array(errors), np.array(stds)
    assert np.mean(np.all(np.abs(errors) <= 2 * stds[:, None], axis=1)) >= 0.9
    assert np.abs(errors).max() < 3.0


def test_register_checks_its_arguments(world):
    _, image = world
    small = crop(image, centred(1100.0, 900.0))
    with pytest.raises(ValueError, match="pixel size"):
        register(image, HeightImage(small.height, 5.0, small.origin))
    with pytest.raises(ValueError, match="moving_mask"):
        register(image, small, moving_mask=np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="moving"):
        register(image, small.height)
    same = register(image, small)                          # the reference's own pixels
    assert same.ok and np.abs(same.shift).max() < 0.05 and same.score > 0.999


def test_a_window_sheared_by_creep_registers_at_its_rows_mean_once_unsheared(world):
    """Creep right after the travel to a relocalisation window shears the new scan's rows
    far more than the full scan's (on scale300 up to 130 nm over 200 rows): registered as
    it is, the shift is that of the rows the content sits in, not the rows' mean that
    the relocalisation takes it for (10-30 nm apart there). Unsheared by the estimate's
    row drift (``relocalise._unsheared``), it is the mean: here the cluster's window with
    a creep tail decaying over its first rows (offset o(t) = A exp(-t / 8 s), one row a
    second, A = (60, -45) nm), registered raw 5 nm off the mean (score 0.87) and within
    0.3 nm of it unsheared (0.97), at seeds 5-7; with twice the tail the raw match is
    refused (0.64) and the unsheared one is 1 nm off."""
    from types import SimpleNamespace

    from nanoasm.executor.relocalise import _unsheared

    surface, image = world
    rng = np.random.default_rng(5)
    corner, shift = centred(1760.0, 550.0), np.array([37.0, -22.0])
    amplitude = np.array([60.0, -45.0])

    def offset(t):                       # scanner position of the layout origin at t: shift + creep tail
        return shift + amplitude * np.exp(-np.asarray(t, float) / 8.0)

    rows = int(SIZE / PIXEL)
    scan = render_scan(surface, PIXEL, window=(*corner, SIZE, SIZE), rng=rng,
                       drift=lambda t: -np.array([offset(v) for v in np.atleast_1d(t)]))
    scan = HeightImage(scan.height, PIXEL, corner)
    mean = np.mean([offset(i) for i in range(rows)], axis=0)
    est = SimpleNamespace(epoch=0.0, offset=offset, unskew=lambda at, tau: np.asarray(at, float))
    raw = register(image, scan)
    unsheared, inside = _unsheared(scan, est, (-0.5, rows - 0.5), (0.0, 1.0, 0.0))
    fixed = register(image, unsheared, moving_mask=inside)
    assert raw.ok and fixed.ok
    assert math.hypot(*(raw.shift - mean)) > 4.0          # the content's rows, not the mean
    assert np.abs(fixed.shift - mean).max() < 0.5, (fixed.shift, mean)
    assert not inside[0].any() and inside[rows // 2, 1:].all()   # pixels taken from beyond the scan are left out
