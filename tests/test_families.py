"""Generated scene families: valid, feasible, deterministic (scene + layout per seed)."""

from __future__ import annotations

import math

import pytest
import shapely

from nanoasm.cad.layout import size_ok
from nanoasm.world.families import FAMILIES, SLOT_CLEARANCE, family, family_case


@pytest.mark.parametrize("name", list(FAMILIES))
def test_every_family_is_valid_feasible_and_deterministic(name):
    scene, layout = family_case(name, 4, drift=0.5)
    again = family_case(name, 4, drift=0.5)
    assert (scene.to_dict(), layout.to_dict()) == (again[0].to_dict(), again[1].to_dict())
    assert scene.to_dict() != family_case(name, 5, drift=0.5)[0].to_dict()
    assert scene.area == layout.area
    # every slot has more compatible objects than slots of its kind, none starts near a slot
    for kind in ("particle", "rod"):
        slots = [t for t in layout.targets if t.kind == kind]
        for t in slots:
            fits = [o for o in scene.objects if o.kind == kind and size_ok(t, o, layout.tolerance)]
            assert len(fits) > len(slots), (name, t.id)
    for o in scene.objects:
        for t in layout.targets:
            gap = shapely.distance(o.geometry(), t.geometry()) - o.radius - t.radius
            assert gap >= SLOT_CLEARANCE - 1e-6
    # the electrodes are obstacles of the scene and keep-outs of the layout
    assert [ob.polygon for ob in scene.obstacles] == [k.polygon for k in layout.keepouts]
    assert bool(scene.obstacles) == family(name).electrodes
    assert math.hypot(*scene.drift.velocity) == pytest.approx(0.5, abs=1e-5)


def test_drift_direction_follows_the_seed_and_speed_the_argument():
    slow, _ = family_case("sparse", 1, drift=0.05)
    fast, _ = family_case("sparse", 1, drift=1.0)
    other, _ = family_case("sparse", 2, drift=1.0)
    assert slow.objects == fast.objects
    assert fast.drift.velocity == pytest.approx((20 * slow.drift.velocity[0], 20 * slow.drift.velocity[1]),
                                                abs=1e-4)
    assert other.drift.velocity != pytest.approx(fast.drift.velocity)


@pytest.mark.parametrize("args, match", [(("nope", 1), "unknown scene family 'nope'; one of tiny"),
                                         (("tiny", -1), "seed must not be negative"),
                                         (("tiny", 1, -0.1), "drift must be finite"),
                                         (("tiny", 1, math.nan), "drift must be finite")])
def test_bad_requests_are_refused(args, match):
    with pytest.raises(ValueError, match=match):
        family_case(*args)
