"""Fixed features for drift: edge and corner sites found in a rendered full scan
(executor/fixed_features.py), the step on one rendered local line and the edge pattern
driven through the scan-pattern protocol (executor/edge_scan.py). Scenes are rendered by
world.render (the simulator's own physics): electrodes 30 nm high, 10 nm pixels, 0.3 nm
noise, 0.2 nm roughness."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely

from nanoasm.bodies import Body
from nanoasm.executor.edge_scan import EdgeScanResult, edge_pattern, locate_step, pattern_samples
from nanoasm.executor.feature_types import EdgeSite, Feature
from nanoasm.executor.fixed_features import find_features
from nanoasm.executor.scan_lines import ScanLine, run_pattern
from nanoasm.world.environment import EnvObstacle
from nanoasm.world.identify import identify
from nanoasm.world.render import make_surface, render_line, render_scan
from nanoasm.world.tipimage import Tip

TIP = Tip(radius=10.0, half_angle=20.0)
H = 30.0
PIXEL = 10.0
AREA = (2560.0, 2560.0)
#: Electrode A inside the image; electrode B cut by its right border.
BOX_A = shapely.box(300.0, 300.0, 1300.0, 800.0)
BOX_B = shapely.box(1800.0, 1200.0, 2600.0, 1700.0)
LINE_TIME = 1.0


def drift(t):
    """Scanner-versus-sample offset during the full scan: 0.1 nm per line in x, 0.05 in y."""
    t = np.asarray(t, float)
    return np.stack([0.1 * t, -0.05 * t], axis=-1)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(11)
    surface = make_surface((), [(BOX_A, H), (BOX_B, H)], AREA, rng=rng)
    image = render_scan(surface, PIXEL, tip=TIP, drift=drift, line_time=LINE_TIME, rng=rng)
    env = identify(image)
    return surface, image, env.obstacles, find_features(image, env.obstacles)


def half_height_distance(surface) -> float:
    """Where a fine noise-free profile across A's right side crosses half height, nm
    beyond the side (the 'true' crossing of the tip-broadened step)."""
    s = np.arange(-40.0, 40.0, 0.01)
    z = render_line(surface, (1300.0 - 40.0, 550.0), (1300.0 + 40.0 - 0.01, 550.0), s.size, tip=TIP,
                    noise_rms=0.0, rng=np.random.default_rng(0))
    k = int(np.argmax(z < H / 2))
    return float(s[k - 1] + (z[k - 1] - H / 2) / (z[k - 1] - z[k]) * 0.01)


def true_side(point, normal) -> tuple[np.ndarray, float]:
    """The outward normal of the electrode's side a site lies on, and the side's
    coordinate along it (the sides are axis-aligned; the sheared image tilts them)."""
    box = BOX_A if BOX_A.distance(shapely.Point(point)) < 60 else BOX_B
    x0, y0, x1, y1 = box.bounds
    axis = np.round(normal)
    side = {(1, 0): x1, (-1, 0): -x0, (0, 1): y1, (0, -1): -y0}[(int(axis[0]), int(axis[1]))]
    return axis, side


# ---------------------------------------------------------------- the full scan

def test_features_on_uncut_sides_only(scene):
    _, image, obstacles, features = scene
    assert [o.edge for o in obstacles] == [False, True]
    kinds = [(f.kind, f.obstacle) for f in features]
    # A: four sides, four corners; B: its three sides inside the image, two corners
    assert kinds.count(("edge", 0)) == 4 and kinds.count(("corner", 0)) == 4
    assert kinds.count(("edge", 1)) == 3 and kinds.count(("corner", 1)) == 2
    assert [f.id for f in features if f.kind == "edge"] == [f"e{i}" for i in range(1, 8)]
    assert [f.id for f in features if f.kind == "corner"] == [f"c{i}" for i in range(1, 7)]
    for f in features:
        assert len(f.sites) == 2 and f.normals().shape == (2, 2)
        n1, n2 = f.normals()
        if f.kind == "edge":
            assert np.dot(n1, n2) > 0.999
        else:
            assert abs(np.dot(n1, n2)) < 0.02
        for site in f.sites:
            assert site.point[0] < AREA[0] - 100.0          # nothing on B's cut side
            assert abs(site.height - H) < 1.5


def test_sites_lie_on_the_half_height_crossing(scene):
    surface, image, _, features = scene
    d = half_height_distance(surface)
    assert 12.0 < d < 13.0                                  # the tip's broadening at 15 nm
    errors = []
    for f in features:
        for site in f.sites:
            axis, side = true_side(site.point, site.normal)
            # the image shows the sample at p + drift(t) at p: the edge moved by -drift
            # at the time its row was scanned
            sample = np.asarray(site.point) + drift(site.row * LINE_TIME)
            errors.append(np.dot(sample, axis) - (side + d))
            assert 0.4 < site.std < 2.0
    errors = np.array(errors)
    assert np.abs(errors).max() < 2.0, errors
    assert np.sqrt(np.mean(errors ** 2)) < 1.2


def test_row_is_where_the_site_was_read(scene):
    _, image, _, features = scene
    for f in features:
        for site in f.sites:
            row = (site.point[1] - image.origin[1]) / image.pixel_size - 0.5
            assert abs(site.row - row) < 0.6


def test_a_particle_on_the_edge_drops_the_site():
    rng = np.random.default_rng(3)
    # two particles against A's top side, at its edge sites' places, none elsewhere
    bodies = [Body("p", "particle", (550.0, 812.0), 24.0), Body("q", "particle", (1050.0, 812.0), 24.0)]
    surface = make_surface(bodies, [(BOX_A, H)], (1600.0, 1100.0), rng=rng)
    image = render_scan(surface, PIXEL, tip=TIP, rng=rng)
    outline = BOX_A.buffer(20.0, join_style="mitre")       # as identification outlines it
    features = find_features(image, [EnvObstacle(tuple(outline.exterior.coords)[:-1], H)])
    top = [f for f in features if f.kind == "edge" and f.normals()[0][1] > 0.9]
    assert not top                                          # both sites of the top edge dropped
    assert sum(f.kind == "edge" for f in features) == 3
    assert sum(f.kind == "corner" for f in features) == 4  # their sites lie clear of the particles


def test_features_check_their_arguments(scene):
    _, image, obstacles, _ = scene
    with pytest.raises(ValueError, match="min_edge"):
        find_features(image, obstacles, min_edge=-1.0)
    with pytest.raises(ValueError, match="image"):
        find_features(image.height, obstacles)
    with pytest.raises(ValueError, match="normal"):
        EdgeSite((0.0, 0.0), (1.0, 1.0), 30.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="std"):
        EdgeSite((0.0, 0.0), (1.0, 0.0), 30.0, 0.0, 0.0)
    site = EdgeSite((0.0, 0.0), (0.0, 1.0), 30.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="kind"):
        Feature("x1", "blob", 0, (site, site))


# ---------------------------------------------------------------- one local line

@pytest.fixture(scope="module")
def plain():
    """Electrode A alone on a rough substrate, and the true half-height distance."""
    surface = make_surface((), [(BOX_A, H)], (1600.0, 1100.0), rng=np.random.default_rng(5))
    return surface, half_height_distance(surface)


def line_across(surface, centre_x, y, reach, rng, *, tilt=0.0, bodies=()):
    """A line along +x (high to low across A's right side) centred at ``centre_x``."""
    if bodies:
        surface = make_surface(bodies, [(BOX_A, H)], (1600.0, 1100.0), rng=np.random.default_rng(5))
    n = int(round(2 * reach)) + 1
    z = render_line(surface, (centre_x - reach, y), (centre_x + reach, y), n, tip=TIP, rng=rng)
    return z + tilt * np.arange(n)


def test_locate_step_accuracy_and_honest_std(plain):
    surface, d = plain
    rng = np.random.default_rng(8)
    errors, stds = [], []
    for _ in range(300):
        off, y, tilt = rng.uniform(-12, 12), rng.uniform(350, 750), rng.uniform(-0.02, 0.02)
        z = line_across(surface, 1300.0 + d + off, y, 40.0, rng, tilt=tilt)
        step = locate_step(z, 1.0, H, expected=40.0)
        assert step.found, step.reason
        errors.append(step.position - (40.0 - off))
        stds.append(step.std)
        assert abs(step.step - H) < 2.0                     # roughness tilts the levels
    errors, stds = np.array(errors), np.array(stds)
    assert np.median(np.abs(errors)) < 0.5
    ratio = np.sqrt(np.mean((errors - errors.mean()) ** 2)) / np.sqrt(np.mean(stds ** 2))
    assert 0.5 < ratio < 2.0, ratio                         # measured 1.17


@pytest.mark.parametrize("diameter", [16.0, 20.0, 30.0])
def test_locate_step_refuses_a_particle_at_the_step(plain, diameter):
    surface, d = plain
    particle = Body("p", "particle", (1300.0 + diameter / 2 + 0.5, 550.0), diameter)
    z = line_across(surface, 1300.0 + d, 550.0, 40.0, np.random.default_rng(1), bodies=[particle])
    step = locate_step(z, 1.0, H)
    assert not step.found
    assert "something on the line" in step.reason


def test_locate_step_refuses_what_is_not_one_step(plain):
    surface, d = plain
    rng = np.random.default_rng(2)
    on_substrate = line_across(surface, 1370.0, 550.0, 40.0, rng)
    on_top = line_across(surface, 1200.0, 550.0, 40.0, rng)
    assert locate_step(on_substrate, 1.0, H).reason == "no step"
    assert locate_step(on_top, 1.0, H).reason == "no step"
    wrong = locate_step(line_across(surface, 1300.0 + d, 550.0, 40.0, rng), 1.0, 12.0)
    assert not wrong.found and wrong.reason.startswith("step height 30 nm, expected 12")
    rising = line_across(surface, 1300.0 + d, 550.0, 40.0, rng)[::-1]
    assert locate_step(rising, 1.0, H).reason == "step rises along the line"
    cut = line_across(surface, 1300.0 + d - 20.0, 550.0, 22.0, rng)
    assert locate_step(cut, 1.0, H).reason == "step cut by the line end"
    far = Body("p", "particle", (1300.0 + d + 30.0, 550.0), 20.0)
    other = line_across(surface, 1300.0 + d + 20.0, 550.0, 60.0, rng, bodies=[far])
    assert locate_step(other, 1.0, H).reason == "several crossings: something on the line"
    with pytest.raises(ValueError, match="spacing"):
        locate_step(on_top, 0.0, H)


# ---------------------------------------------------------------- the local pattern

def scanner_of(surface, offset, rng, log=None):
    """``scan_line(a, b, n)`` in the scanner frame: a sample point p sits at p + offset."""
    def scan_line(a, b, n):
        if log is not None:
            log.append((a, b, n))
        sa = (a[0] - offset[0], a[1] - offset[1])
        sb = (b[0] - offset[0], b[1] - offset[1])
        return render_line(surface, sa, sb, n, tip=TIP, rng=rng)
    return scan_line


def test_local_lines_recover_the_drift_at_full_scan_sites(scene):
    surface, image, _, features = scene
    rng = np.random.default_rng(4)
    for f in features:
        # the sites as the full scan showed them, taken back to the sample: the drift of
        # their row undone (the caller's business, with the row's time)
        sites = [(np.asarray(s.point) + drift(s.row * LINE_TIME), np.asarray(s.normal), s.height)
                 for s in f.sites]
        d_true = rng.uniform(-15, 15, 2)
        d_est = d_true + rng.uniform(-8, 8, 2)         # the filter's estimate, off by a little
        placed = [(p + d_est, n, h) for p, n, h in sites]
        result = run_pattern(edge_pattern(placed, 40.0, site_stds=[s.std for s in f.sites]),
                             scanner_of(surface, d_true, rng))
        assert isinstance(result, EdgeScanResult)
        assert result.found, (f.id, result.reason)
        expected = f.normals() @ (d_true - d_est)
        assert np.abs(result.offsets - expected).max() < 2.0, (f.id, result.offsets, expected)
        if f.kind == "corner":                              # both coordinates
            solved = np.linalg.solve(f.normals(), result.offsets)
            assert np.abs(solved - (d_true - d_est)).max() < 2.5


def test_edge_pattern_drives_the_protocol(plain):
    surface, d = plain
    sites = [((1300.0 + d, 450.0), (1.0, 0.0), H), ((1300.0 + d, 650.0), (1.0, 0.0), H)]
    log = []
    pattern = edge_pattern(sites, 30.0, spacing=1.0)
    first = next(pattern)
    assert isinstance(first, ScanLine) and first.role == "E0"
    assert first.a == (1300.0 + d - 30.0, 450.0) and first.b == (1300.0 + d + 30.0, 450.0)
    with pytest.raises(ValueError, match="shape"):
        pattern.send(np.zeros(3))
    scan = scanner_of(surface, (3.0, 0.0), np.random.default_rng(1), log)
    result = run_pattern(edge_pattern(sites, 30.0), scan)
    assert result.found and result.ok.all() and result.lines == 2
    assert result.samples == pattern_samples(30.0, 1.0, 2) == sum(n for _, _, n in log) == 2 * 61
    assert np.allclose(result.offsets, 3.0, atol=0.5)
    assert np.all(result.stds < 0.5)


def test_edge_pattern_refuses_disagreeing_sites(plain):
    surface, d = plain
    scan = scanner_of(surface, (0.0, 0.0), np.random.default_rng(2))
    # the second site placed 6 nm off: the two lines of one edge disagree
    sites = [((1300.0 + d, 450.0), (1.0, 0.0), H), ((1300.0 + d + 6.0, 650.0), (1.0, 0.0), H)]
    result = run_pattern(edge_pattern(sites, 30.0, site_stds=0.8), scan)
    assert result.ok.all() and not result.found
    assert "disagree" in result.reason
    # a particle at the step on the second line
    bodies = [Body("p", "particle", (1300.0 + 10.5, 650.0), 20.0)]
    cluttered = make_surface(bodies, [(BOX_A, H)], (1600.0, 1100.0), rng=np.random.default_rng(5))
    sites[1] = ((1300.0 + d, 650.0), (1.0, 0.0), H)
    scan = scanner_of(cluttered, (0.0, 0.0), np.random.default_rng(2))
    result = run_pattern(edge_pattern(sites, 30.0), scan)
    assert not result.found and list(result.ok) == [True, False]
    assert result.reason.startswith("line E1:") and math.isnan(result.offsets[1])


def test_edge_pattern_checks_its_arguments():
    with pytest.raises(ValueError, match="sites_scanner"):
        edge_pattern([], 30.0)
    with pytest.raises(ValueError, match=r"sites_scanner\[0\] normal"):
        edge_pattern([((0.0, 0.0), (0.0, 0.0), H)], 30.0)
    with pytest.raises(ValueError, match="reach"):
        edge_pattern([((0.0, 0.0), (1.0, 0.0), H)], -1.0)
    with pytest.raises(ValueError, match="site_stds"):
        edge_pattern([((0.0, 0.0), (1.0, 0.0), H)], 30.0, site_stds=-1.0)
    assert pattern_samples(30.0, 1.0, 0) == 0
