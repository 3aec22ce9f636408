"""Identification: simulated scans against their truth, special shapes, real AFM images."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.instrument import HeightImage
from nanoasm.world.identify import analyse, default_cut, fit_ball, fit_capsule, identify, level
from nanoasm.world.render import make_surface, render_scan
from nanoasm.world.tipimage import Tip, ball_image, ball_reach

TIP = Tip(10.0, 20.0)
#: The pixel size of a 10 x 10 µm scan at 512 x 512, as a dry-run takes it.
PIXEL = 10000.0 / 512


def _broadening(body: Body) -> float:
    """How far the body's image reaches past its footprint."""
    return float(ball_reach(body.radius, 0.0, TIP)) - body.radius


def random_scene(rng: np.random.Generator, area: float = 5000.0, particles: int = 12, rods: int = 4,
                 obstacles: int = 2, border: int = 2):
    """Particles 40-150 nm, rods with 3 <= L/d <= 14, irregular plateaus, all apart by
    more than their images' broadening; plus ``border`` particles cut by the image edge."""
    obs: list[tuple[shapely.Polygon, float]] = []
    while len(obs) < obstacles:
        c = rng.uniform(700, area - 700, 2)
        ang = np.sort(rng.uniform(0, 2 * np.pi, int(rng.integers(5, 9))))
        rad = rng.uniform(120, 400, ang.size)
        poly = shapely.Polygon(np.column_stack([c[0] + rad * np.cos(ang), c[1] + rad * np.sin(ang)]))
        if poly.is_valid and all(poly.distance(o) > 300 for o, _ in obs):
            obs.append((poly, float(rng.uniform(10, 60))))
    bodies: list[Body] = []

    def free(b: Body, margin: float) -> bool:
        g = b.geometry()
        if any(g.distance(o) < b.radius + _broadening(b) + 60 for o, _ in obs):
            return False
        return all(g.distance(o.geometry()) > b.radius + o.radius + _broadening(b) + _broadening(o) + 20
                   for o in bodies) and margin > 0

    for i in range(particles + rods):
        for _ in range(1000):
            if i < rods:
                d, sigma = rng.uniform(30, 100), rng.uniform(3, 14)
                b = Body(f"t{i}", "rod", tuple(rng.uniform(0, area, 2)), d, rng.uniform(0, 180), sigma * d)
            else:
                b = Body(f"t{i}", "particle", tuple(rng.uniform(0, area, 2)), rng.uniform(40, 150))
            x0, y0, x1, y1 = b.bounds()
            reach = _broadening(b) + 2 * PIXEL
            if free(b, min(x0, y0, area - x1, area - y1) - reach):
                bodies.append(b)
                break
    cut: list[Body] = []
    for k in range(border):
        for _ in range(1000):
            d = rng.uniform(60, 150)
            t = rng.uniform(500, area - 500)
            at = [(0.0, t), (t, 0.0), (area, t), (t, area)][(k + int(rng.integers(4))) % 4]
            b = Body(f"e{k}", "particle", at, d)
            if free(b, 1.0):
                bodies.append(b)
                cut.append(b)
                break
    return bodies, obs, {b.id for b in cut}


def _angle_error(a: float, b: float) -> float:
    return abs((a - b + 90.0) % 180.0 - 90.0)


def test_identifies_100_random_scenes_exactly():
    rng = np.random.default_rng(20240607)
    worst = {"centre": 0.0, "diameter": 0.0, "angle": 0.0, "length": 0.0}
    counts = {"particle": 0, "rod": 0, "obstacle": 0, "edge": 0}
    for scene in range(100):
        bodies, obstacles, cut = random_scene(rng)
        surface = make_surface(bodies, obstacles, (5000.0, 5000.0), rng=rng)
        img = render_scan(surface, PIXEL, line_offset_prob=0.02, line_offset_rms=1.0, rng=rng)
        env = identify(img)
        found = list(env.objects)
        for b in bodies:
            near = [o for o in found if math.dist(o.at, b.at) < 25.0]
            if b.id in cut:
                assert all(o.edge for o in near), (scene, b, near)
                counts["edge"] += len(near)
                found = [o for o in found if o not in near]
                continue
            assert len(near) == 1, f"scene {scene}: {b} found as {near}"
            o = near[0]
            assert o.kind == b.kind and not o.edge, (scene, b, o)
            worst["centre"] = max(worst["centre"], math.dist(o.at, b.at))
            worst["diameter"] = max(worst["diameter"], abs(o.diameter / b.diameter - 1))
            if b.kind == "rod":
                worst["angle"] = max(worst["angle"], _angle_error(o.angle, b.angle))
                worst["length"] = max(worst["length"], abs(o.length - b.length))
            counts[b.kind] += 1
            found.remove(o)
        assert not found, f"scene {scene}: invented {found}"
        for poly, height in obstacles:
            hits = [o for o in env.obstacles if shapely.Polygon(o.polygon).intersects(poly)]
            assert len(hits) == 1, (scene, poly.wkt, len(hits))
            assert hits[0].height == pytest.approx(height, abs=1.0)
            assert shapely.Polygon(hits[0].polygon).is_valid
            counts["obstacle"] += 1
        assert len(env.obstacles) == len(obstacles)
    assert worst["centre"] < 2.0 and worst["diameter"] < 0.05 and worst["angle"] < 1.0, worst
    assert worst["length"] < 10.0, worst
    assert counts["rod"] >= 300 and counts["particle"] >= 1000 and counts["edge"] >= 100, counts


def test_merged_images_split_into_separate_objects_but_touching_ones_are_an_aggregate():
    rng = np.random.default_rng(3)
    a = Body("a", "particle", (400.0, 500.0), 150.0)
    b = Body("b", "particle", (600.0, 500.0), 150.0)             # 50 nm gap: images overlap
    env = identify(render_scan(make_surface([a, b], [], (1000.0, 1000.0), rng=rng), 5.0, rng=rng))
    assert sorted(o.kind for o in env.objects) == ["particle", "particle"]
    for o, t in zip(sorted(env.objects, key=lambda o: o.at[0]), (a, b)):
        assert math.dist(o.at, t.at) < 2.0 and o.diameter == pytest.approx(150.0, rel=0.02)
    c = Body("c", "particle", (400.0, 500.0), 100.0)
    d = Body("d", "particle", (500.0, 500.0), 100.0)             # in contact
    env = identify(render_scan(make_surface([c, d], [], (1000.0, 1000.0), rng=rng), 5.0, rng=rng))
    assert env.objects == () and len(env.obstacles) == 1


def test_rod_limit_and_the_uncertain_band():
    rng = np.random.default_rng(4)
    rods = [Body("r20", "rod", (1500.0, 700.0), 40.0, 10.0, 800.0),     # sigma 20: still a rod
            Body("w30", "rod", (1500.0, 1500.0), 40.0, 170.0, 1200.0),  # sigma 30: a wire
            Body("r5", "rod", (1500.0, 2300.0), 40.0, 90.0, 200.0)]
    img = render_scan(make_surface(rods, [], (3000.0, 3000.0), rng=rng), PIXEL, rng=rng)
    env = identify(img)
    by = {b.id: min(env.objects, key=lambda o: math.dist(o.at, b.at)) for b in rods}
    assert by["r20"].kind == "rod" and by["w30"].kind == "wire" and by["r5"].kind == "rod"
    assert by["r20"].confidence < by["r5"].confidence
    assert by["w30"].length == pytest.approx(1200.0, abs=10.0)
    assert identify(img, rod_limit=35.0).objects[1].kind == "rod"


def _tube_image(points: np.ndarray, a: float, shape: tuple[int, int], ps: float, rng) -> HeightImage:
    """Image of a flexible tube of radius ``a`` along a polyline (a union of balls)."""
    ys, xs = (np.arange(n) * ps + ps / 2 for n in shape)
    gx, gy = np.meshgrid(xs, ys)
    z = np.zeros(shape)
    for p in points:
        z = np.maximum(z, ball_image(np.hypot(gx - p[0], gy - p[1]), a, TIP))
    return HeightImage(z + rng.normal(0, 0.1, shape), ps)


def test_a_curved_strand_is_a_wire_and_a_ring_is_an_obstacle():
    rng = np.random.default_rng(5)
    t = np.linspace(0, 0.75 * np.pi, 400)
    arc = np.column_stack([300 + 200 * np.cos(t), 150 + 200 * np.sin(t)])
    env = identify(_tube_image(arc, 3.0, (200, 200), 3.0, rng))
    assert [o.kind for o in env.objects] == ["wire"] and env.obstacles == ()
    assert env.objects[0].length == pytest.approx(0.75 * np.pi * 200, rel=0.1)
    t = np.linspace(0, 2 * np.pi, 600)
    ring = np.column_stack([300 + 150 * np.cos(t), 300 + 150 * np.sin(t)])
    env = identify(_tube_image(ring, 3.0, (200, 200), 3.0, rng))
    assert env.objects == () and len(env.obstacles) == 1
    poly = shapely.Polygon(env.obstacles[0].polygon)
    assert poly.contains(shapely.Point(300, 300))                  # filled: the hole is no way through


def test_shape_fits_recover_exact_parameters():
    rng = np.random.default_rng(6)
    x, y = rng.uniform(-150, 150, (2, 3000))
    z = np.maximum(ball_image(np.hypot(x - 3.3, y + 1.7), 40.0, Tip(14.0)), 0) + rng.normal(0, 0.1, x.size)
    f = fit_ball(x, y, z, centre=(0.0, 0.0), radius=35.0, tip=TIP, reach=100.0)
    assert f.centre == pytest.approx((3.3, -1.7), abs=0.05)
    assert f.diameter == pytest.approx(80.0, abs=0.1) and f.tip_radius == pytest.approx(14.0, abs=0.5)
    th = math.radians(63.0)
    u = (x - 5) * math.cos(th) + (y - 8) * math.sin(th)
    v = -(x - 5) * math.sin(th) + (y - 8) * math.cos(th)
    z = np.maximum(ball_image(np.hypot(np.maximum(np.abs(u) - 60, 0), v), 20.0, TIP), 0)
    f = fit_capsule(x, y, z + rng.normal(0, 0.1, x.size), centre=(0.0, 0.0), angle=55.0,
                    half_length=50.0, radius=18.0, tip=TIP, reach=100.0)
    assert f.angle == pytest.approx(63.0, abs=0.05) and f.length == pytest.approx(160.0, abs=0.3)
    assert f.centre == pytest.approx((5.0, 8.0), abs=0.1)


def test_levelling_removes_tilt_bow_and_line_offsets_under_objects():
    rng = np.random.default_rng(7)
    bodies = [Body(f"p{i}", "particle", (x, y), 80.0)
              for i, (x, y) in enumerate([(500, 500), (1500, 700), (900, 1500), (1700, 1700)])]
    surface = make_surface(bodies, [], (2000.0, 2000.0), rng=rng)
    img = render_scan(surface, 10.0, noise_rms=0.3, line_offset_prob=0.2, line_offset_rms=3.0, rng=rng)
    clean = render_scan(surface, 10.0, noise_rms=0.0, rng=rng).height
    gy, gx = np.mgrid[0:200, 0:200]
    raw = img.height + 0.05 * gx - 0.02 * gy + 40.0
    lev = level(raw)
    flat = lev.height[lev.substrate]
    assert abs(np.median(flat)) < 0.05 and lev.sigma == pytest.approx(0.36, abs=0.05)
    # Offsets, tilt and bias gone, objects kept: what is left is the per-sample noise.
    assert np.abs(lev.height - clean).max() < 6 * 0.3
    assert np.std(lev.height - clean) == pytest.approx(0.3, rel=0.1)
    cut = default_cut(lev)
    assert cut == pytest.approx(5 * lev.sigma, abs=0.3) and cut >= 0.5
    env = identify(HeightImage(raw, 10.0))
    assert len(env.objects) == 4 and all(o.diameter == pytest.approx(80.0, rel=0.02) for o in env.objects)


@pytest.mark.parametrize("x0", [500.0, 300.0])
def test_a_plateau_over_most_of_each_row_is_not_taken_for_the_substrate(x0):
    rng = np.random.default_rng(12)
    p = Body("p", "particle", (x0 / 2, 300.0), 80.0)
    electrode = [(x0, -10), (1010, -10), (1010, 1010), (x0, 1010)]
    img = render_scan(make_surface([p], [(electrode, 30.0)], (1000.0, 1000.0), rng=rng), 5.0,
                      line_offset_prob=0.1, line_offset_rms=2.0, rng=rng)
    gy, gx = np.mgrid[0:200, 0:200]
    env = identify(HeightImage(img.height + 0.03 * gx + 0.05 * gy, 5.0))
    assert len(env.objects) == 1 and env.objects[0].diameter == pytest.approx(80.0, rel=0.02)
    assert math.dist(env.objects[0].at, p.at) < 1.0
    assert len(env.obstacles) == 1 and env.obstacles[0].edge
    assert env.obstacles[0].height == pytest.approx(30.0, abs=1.0)


def test_electrode_pads_over_most_of_some_rows_but_little_of_the_image():
    """Two pads with a gap, as under a bowtie: 7 % of the image, but 56 % of the rows
    they lie in. Row medians alone align those rows to the pads' top, sink the gap by the
    pad height and turn the particles there into obstacles."""
    rng = np.random.default_rng(5)
    inside = [Body(f"g{i}", "particle", (x, y), 90.0) for i, (x, y) in
              enumerate([(1900.0, 2150.0), (2900.0, 2400.0), (2500.0, 2850.0)])]
    outside = [Body("a", "particle", (1000.0, 1000.0), 90.0), Body("b", "particle", (4000.0, 4000.0), 90.0)]
    pads = [([(0, 2200), (1400, 2200), (1400, 2800), (0, 2800)], 30.0),
            ([(3600, 2200), (5000, 2200), (5000, 2800), (3600, 2800)], 30.0)]
    img = render_scan(make_surface(inside + outside, pads, (5000.0, 5000.0), rng=rng), 10.0, rng=rng)
    env = identify(img)
    assert sorted(o.kind for o in env.objects) == ["particle"] * 5
    for b in inside + outside:
        assert min(math.dist(o.at, b.at) for o in env.objects) < 2.0
    assert len(env.obstacles) == 2


def test_obstacle_outline_and_edge_flags():
    rng = np.random.default_rng(8)
    square = [(1000, 1000), (1600, 1000), (1600, 1400), (1000, 1400)]
    edge_block = [(-100, 200), (300, 200), (300, 600), (-100, 600)]
    p = Body("p", "particle", (2000.0, 0.0), 100.0)                # cut by the bottom edge
    img = render_scan(make_surface([p], [(square, 30.0), (edge_block, 20.0)], (2500.0, 2500.0),
                                   rng=rng), 10.0, rng=rng)
    env = identify(img)
    inner = [o for o in env.obstacles if not o.edge]
    assert len(inner) == 1 and inner[0].height == pytest.approx(30.0, abs=0.5)
    poly = shapely.Polygon(inner[0].polygon)
    truth = shapely.Polygon(square)
    assert poly.is_valid and poly.contains(truth.buffer(-5))
    assert poly.buffer(-0.1).within(truth.buffer(40))               # tip broadening only
    assert [o.edge for o in env.obstacles].count(True) == 1
    assert len(env.objects) == 1 and env.objects[0].edge and env.objects[0].confidence <= 0.5


def test_pixel_size_option_and_frame_origin():
    rng = np.random.default_rng(9)
    p = Body("p", "particle", (700.0, 300.0), 90.0)
    img = render_scan(make_surface([p], [], (1000.0, 1000.0), rng=rng), 5.0, rng=rng)
    moved = HeightImage(img.height, 5.0, (1000.0, -500.0))
    # the environment's (0, 0) is the image's lower-left corner, whatever its origin:
    # its objects lie in its area (issue 15: they lay at the origin's offset, outside it)
    o = identify(moved).objects[0]
    assert o.at == pytest.approx((700.0, 300.0), abs=1.0)
    o = identify(moved, pixel_size=10.0).objects[0]                 # everything doubles
    assert o.at == pytest.approx((1400.0, 600.0), abs=2.0)
    assert identify(moved).area == (1000.0, 1000.0)


def test_bad_options_and_images_are_input_errors():
    img = HeightImage(np.zeros((10, 10)), 1.0, source="scan.npz")
    for kw, key in [({"cut": -1.0}, "cut"), ({"min_area": -2.0}, "min_area"),
                    ({"pixel_size": 0.0}, "pixel_size"), ({"rod_limit": 0.5}, "rod_limit"),
                    ({"tip_radius": float("nan")}, "tip_radius"),
                    ({"tip_half_angle": 95.0}, "tip_half_angle")]:
        with pytest.raises(InputError, match=key) as e:
            identify(img, **kw)
        assert str(e.value).startswith("scan.npz: ")
    with pytest.raises(InputError, match="no finite"):
        identify(HeightImage(np.full((4, 4), np.nan), 1.0))
    assert identify(img).objects == ()                              # a flat image is fine


def test_min_area_and_min_height_filters():
    rng = np.random.default_rng(10)
    small = Body("s", "particle", (300.0, 300.0), 6.0)
    big = Body("b", "particle", (700.0, 700.0), 60.0)
    img = render_scan(make_surface([small, big], [], (1000.0, 1000.0), roughness_rms=0.0, rng=rng),
                      2.0, noise_rms=0.05, rng=rng)
    assert len(identify(img, cut=1.0).objects) == 2
    assert len(identify(img, cut=1.0, min_height=10.0).objects) == 1
    area_small = math.pi * float(ball_reach(3.0, 1.0, TIP)) ** 2
    assert len(identify(img, cut=1.0, min_area=1.5 * area_small).objects) == 1


# ---------------------------------------------------------------- real AFM images

def test_minicircle_matches_topostats_grains(shared_afm):
    from nanoasm.world.readers import read_height_image

    img = read_height_image(shared_afm / "minicircle_cropped_flattened.npy", pixel_size=0.4940029296875)
    an = analyse(img, cut=1.0, min_area=20.0)
    assert an.grains.max() == 9                                     # TopoStats: 9 grains
    ref = np.flipud(np.load(shared_afm / "minicircle_cropped_masks_above.npy"))
    assert ref.max() == 6
    for k in range(1, 7):
        mask = ref == k
        labels, counts = np.unique(an.grains[mask], return_counts=True)
        ours = an.grains == labels[np.argmax(counts)]
        assert np.count_nonzero(mask & ours) / np.count_nonzero(mask | ours) > 0.9
    env = an.environment
    interior = [o for o in env.objects if not o.edge] + [o for o in env.obstacles if not o.edge]
    assert len(interior) == 6
    assert all(o.kind != "rod" for o in env.objects if not o.edge)
    assert sum(1 for o in env.obstacles if not o.edge) >= 3         # the three rings


def test_sample_g_particles_and_piles(shared_afm):
    from nanoasm.world.readers import read_height_image

    env = identify(read_height_image(shared_afm / "sample_g.gwy"))
    particles = [o for o in env.objects if o.kind == "particle"]
    assert 30 <= len(particles) <= 60
    assert all(5.0 <= p.diameter <= 60.0 for p in particles)
    assert 8.0 <= float(np.median([p.diameter for p in particles])) <= 30.0
    piles = sorted(env.obstacles, key=lambda o: shapely.Polygon(o.polygon).area)[-2:]
    assert piles[-1].height > 100.0 and shapely.Polygon(piles[-1].polygon).area > 2e5
    assert shapely.Polygon(piles[0].polygon).area > 3e4
    for o in env.objects:
        assert not any(shapely.Polygon(p.polygon).contains(shapely.Point(o.at)) for p in piles)
    assert all(o.kind != "rod" for o in env.objects)


@pytest.mark.parametrize("name,kw,low,high", [
    ("sample_1_um_scale.stp", {}, 50, 200),
    ("file.stp", {}, 8, 40),
    ("file.jpk-qi-image", {}, 12, 40),
    ("example_catenanes.npy", {"pixel_size": 0.488}, 1, 6),
])
def test_other_real_images_give_a_plausible_count(shared_afm, name, kw, low, high):
    from nanoasm.world.readers import read_height_image

    env = identify(read_height_image(shared_afm / name, **kw))
    assert low <= len(env.objects) + len(env.obstacles) <= high
    for o in env.obstacles:
        assert shapely.Polygon(o.polygon).is_valid


def test_environment_round_trips_through_the_env_format(tmp_path):
    from nanoasm.world.environment import load_environment

    rng = np.random.default_rng(11)
    bodies, obstacles, _ = random_scene(rng)
    env = identify(render_scan(make_surface(bodies, obstacles, (5000.0, 5000.0), rng=rng), PIXEL, rng=rng))
    env.save(tmp_path / "env.json")
    back = load_environment(tmp_path / "env.json")
    assert back.objects == env.objects and back.area == env.area
    assert [o.polygon for o in back.obstacles] == [tuple(map(tuple, o.polygon)) for o in env.obstacles]


def test_real_environment_is_valid_env_json(shared_afm, tmp_path):
    from nanoasm.world.environment import load_environment
    from nanoasm.world.readers import read_height_image

    for name in ("sample_g.gwy", "file.jpk-qi-image"):
        env = identify(read_height_image(shared_afm / name))
        env.save(tmp_path / "env.json")
        back = load_environment(tmp_path / "env.json")
        assert len(back.objects) == len(env.objects) and len(back.obstacles) == len(env.obstacles)
        assert back.source == str(shared_afm / name)


@pytest.mark.parametrize("seed", range(6))
def test_the_grains_tops_are_ndimages_maxima(seed):
    """A grain's top, taken from the labelled pixels alone, is ``ndimage.maximum`` of its
    label, to the bit, in float32 and float64 scans with holes (NaN) and grains of one
    pixel; and the grains ``min_height`` keeps are the ones whose maximum reaches it."""
    from scipy import ndimage

    from nanoasm.world.identify.grains import EIGHT, _tops, label_grains

    rng = np.random.default_rng(seed)
    h = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (120, 90)), 2.0) * 40.0
    h[rng.random(h.shape) < 0.01] = np.nan
    h = h.astype(np.float32 if seed % 2 else np.float64)
    labels, n = ndimage.label(h > 1.0, EIGHT)
    assert n > 5
    np.testing.assert_array_equal(_tops(h, labels, n), ndimage.maximum(h, labels, np.arange(1, n + 1)))
    kept, m = label_grains(h, 1.0, min_height=6.0)
    tops = ndimage.maximum(h, labels, np.arange(1, n + 1))
    rows = [box[0].stop - box[0].start for box in ndimage.find_objects(labels)]
    assert m == sum(1 for t, r in zip(tops, rows) if t >= 6.0 and r >= 2) > 0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=0, max_size=300),
       st.sampled_from([np.float64, np.float32]))
def test_levellings_median_is_numpys(values, dtype):
    """One selection of the two middle elements, the NaN check on the upper half: the value
    of ``np.median``, NaN and infinities included, in float64 and float32."""
    from nanoasm.world.identify.levelling import median

    with np.errstate(all="ignore"):
        a = np.array(values, dtype=np.float64).astype(dtype)
        want = np.median(a) if a.size else math.nan
    got = median(a)
    assert (math.isnan(got) and math.isnan(want)) or got == want


@pytest.mark.parametrize("n", [20_000, 20_001, 1_000_000, 1_000_001])
def test_levellings_median_is_numpys_on_large_arrays(n):
    """Arrays large enough that the selection does not sort them whole, with ties."""
    from nanoasm.world.identify.levelling import median

    rng = np.random.default_rng(n)
    a = np.round(rng.normal(0.0, 1.0, n), 2)
    assert median(a) == np.median(a)
    a[rng.integers(n)] = np.nan
    assert math.isnan(median(a))


@pytest.mark.parametrize("seed", range(4))
def test_levellings_surface_rows_and_mask_are_the_plain_computations(seed):
    """The surface evaluated band by band, the rows' medians one by one and the mask grown
    by a maximum filter equal, to the bit, the whole-image outer products, ``np.nanmedian``
    and ``binary_dilation`` they replace (an image whose rows are no multiple of a band)."""
    from scipy import ndimage

    from nanoasm.world.identify.levelling import _powers, align_rows, fit_surface

    rng = np.random.default_rng(seed)
    ny, nx = 150 + 37 * seed, 90 + 11 * seed
    z = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (ny, nx)), 1.5) * 5.0 + rng.normal(0.0, 0.1, (ny, nx))
    use = rng.random((ny, nx)) > 0.3
    use[3] = False                               # a row with nothing usable: interpolated
    for order in (0, 1, 2, 3):                   # a factor of ones broadcast in the bands: the same sums
        iy, ix = np.nonzero(use)
        pick = np.linspace(0, iy.size - 1, 500).astype(int)
        iy, ix = iy[pick], ix[pick]
        xs, ys = np.linspace(-1.0, 1.0, nx), np.linspace(-1.0, 1.0, ny)
        a = np.stack([xs[ix] ** i * ys[iy] ** j for i, j in _powers(order)], axis=-1)
        coef = np.linalg.lstsq(a, z[iy, ix], rcond=None)[0]
        want = np.zeros_like(z)
        for (i, j), k in zip(_powers(order), coef):
            want += k * np.outer(ys ** j, xs ** i)
        assert fit_surface(z, use, order, max_points=500).tobytes() == want.tobytes()
    enough = np.count_nonzero(use, axis=1) >= 5
    offs = np.full(ny, np.nan)
    offs[enough] = np.nanmedian(np.where(use[enough], z[enough], np.nan), axis=1)
    filled = np.interp(np.arange(ny), np.nonzero(enough)[0], offs[enough])
    np.testing.assert_array_equal(align_rows(z, use, 0), np.broadcast_to(filled[:, None], z.shape))
    objects = rng.random((ny, nx)) > 0.97
    for grow in (1, 2, 3):
        np.testing.assert_array_equal(ndimage.maximum_filter(objects, size=2 * grow + 1),
                                      ndimage.binary_dilation(objects, ndimage.generate_binary_structure(2, 2),
                                                              iterations=grow))


def _plain_level(height, plane_order=1, line_order=0, iterations=6, k_mask=3.0, grow=2, floor=None):
    """``level`` as whole-image steps, each a new array: the surface, the rows' correction
    and the centre subtracted, the substrate's medians on a copy."""
    from scipy import ndimage

    from nanoasm.world.identify.levelling import CUT_FLOOR, align_rows, fit_surface, initial_substrate

    floor = CUT_FLOOR if floor is None else floor
    z = np.asarray(height, dtype=float)
    valid = np.isfinite(z)
    z = np.where(valid, z, np.median(z[valid]))
    use = initial_substrate(z, valid)
    sigma = 0.0
    for _ in range(iterations):
        z = z - fit_surface(z, use, plane_order)
        z = z - align_rows(z, use, line_order)
        base = z[use]
        centre = np.median(base)
        sigma = float(1.4826 * np.median(np.abs(base - centre)))
        z = z - centre
        objects = ndimage.binary_dilation(np.abs(z) > max(k_mask * sigma, floor / 2),
                                          ndimage.generate_binary_structure(2, 2), iterations=grow) if grow \
            else np.abs(z) > max(k_mask * sigma, floor / 2)
        new_use = valid & ~objects
        if np.count_nonzero(new_use) < max(10, 0.05 * z.size):
            break
        if np.count_nonzero(new_use != use) <= 1e-3 * z.size:
            use = new_use
            break
        use = new_use
    return np.where(valid, z, 0.0), use, sigma


@pytest.mark.parametrize("seed", range(5))
def test_level_in_place_is_the_plain_computation(seed):
    """``level`` changes its own copy in place (the surface subtracted a band at a time, one
    offset a row, the substrate's medians selected in the gathered copy): the levelled
    image, substrate and sigma of the whole-image steps, to the bit, for every line order,
    with holes, in float32, and with no mask growth."""
    from nanoasm.world.identify.levelling import MAD_TO_SIGMA, level

    assert MAD_TO_SIGMA == 1.4826
    rng = np.random.default_rng(seed)
    ny, nx = 150 + 41 * seed, 120 + 23 * seed          # more rows than a band, not a multiple of one
    yy, xx = np.mgrid[0:ny, 0:nx]
    z = 0.01 * xx + 0.02 * yy + rng.normal(0, 0.3, (ny, nx)) + rng.normal(0, 2, ny)[:, None]
    for _ in range(25):
        cy, cx = rng.integers(0, ny), rng.integers(0, nx)
        z += 8 * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / 50.0)
    if seed % 2:
        z[rng.random((ny, nx)) < 0.01] = np.nan
    if seed == 4:
        z = z.astype(np.float32)
    before = z.copy()
    for kw in ({}, {"line_order": 1}, {"plane_order": 2, "line_order": 2}, {"plane_order": 0}, {"grow": 0}):
        got = level(z, **kw)
        height, use, sigma = _plain_level(z, **kw)
        np.testing.assert_array_equal(got.height, height)
        np.testing.assert_array_equal(got.substrate, use)
        assert got.sigma == sigma
    np.testing.assert_array_equal(z, before)             # the caller's heights untouched


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6), min_size=0, max_size=200), st.sampled_from([np.float64, np.float32]))
def test_centre_and_sigma_in_the_callers_array_are_those_on_a_copy(values, dtype):
    from nanoasm.world.identify.levelling import centre_sigma

    a = np.array(values, dtype=np.float64).astype(dtype)
    want = centre_sigma(a.copy())
    got = centre_sigma(a, overwrite=True)
    assert (got[0] == want[0] or (math.isnan(got[0]) and math.isnan(want[0]))) and got[1] == want[1]
