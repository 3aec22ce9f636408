"""Scene v1: validation with the same rigour as layouts; random scenes are valid."""

from __future__ import annotations

import copy
import math
import tomllib

import pytest
from hypothesis import given, strategies as st

from nanoasm.errors import InputError
from nanoasm.world.random_scene import SceneSpec, random_scene
from nanoasm.world.params import DriftParams, WorldParams
from nanoasm.world.scene import load_scene, scene_from_dict


def base() -> dict:
    return {
        "format": "nanoasm.scene/1",
        "area": [10000, 10000],
        "seed": 7,
        "object": [
            {"id": "a", "kind": "particle", "at": [3000, 4000], "diameter": 100},
            {"kind": "rod", "at": [6000, 6000], "angle": 75, "length": 1300, "diameter": 100},
        ],
        "obstacle": [{"polygon": [[100, 100], [600, 100], [600, 300], [100, 300]], "height": 30}],
        "drift": {"velocity": [0.08, -0.05], "random_walk": 0.05},
        "noise": {"height_rms": 0.3},
    }


def with_(path: str, value) -> dict:
    data = copy.deepcopy(base())
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    node = data
    for k in keys[:-1]:
        node = node[k]
    if value is None:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return data


def test_valid_scene_and_default_ids():
    s = scene_from_dict(base(), "s.toml")
    assert [o.id for o in s.objects] == ["a", "o2"]
    assert s.drift == DriftParams((0.08, -0.05), 0.05)
    assert s.seed == 7
    assert scene_from_dict(tomllib.loads(s.dumps_toml())) == s


def test_optional_tables_stay_absent():
    data = base()
    for k in ("drift", "noise", "seed", "obstacle"):
        del data[k]
    s = scene_from_dict(data)
    assert s.params == WorldParams() and s.seed is None
    assert "drift" not in s.to_dict() and "noise" not in s.to_dict()
    assert scene_from_dict(s.to_dict()) == s


CASES = [
    ("area", [0, 10000], "area", "width must be positive"),
    ("area", [10000, 0.0], "area", "height must be positive"),
    ("seed", -1, "seed", "must not be negative"),
    ("seed", 1.5, "seed", "must be an integer"),
    ("drift.velocity", [math.nan, 0], "drift.velocity", "x must be finite"),
    ("drift.velocity", [0, math.inf], "drift.velocity", "y must be finite"),
    ("drift.random_walk", math.inf, "drift.random_walk", "must be finite"),
    ("drift.random_walk", -0.1, "drift.random_walk", "must not be negative"),
    ("drift.speed", 1, "drift.speed", "unknown key"),
    ("noise.height_rms", math.nan, "noise.height_rms", "must be finite"),
    ("noise.height_rms", -1, "noise.height_rms", "must not be negative"),
    ("object.0.at", [3000, 9970], "object[1]", "outside the area"),
    ("object.1.at", [3000, 4050], "object[2]", "overlaps object 'a'"),
    ("object.1.at", [9900, 6000], "object[2]", "outside the area"),
    ("object.0.at", [350, 200], "object[1]", "overlaps obstacle[1]"),
    ("object.0.kind", "wire", "object[1].kind", "must be one of"),
    ("object.1.length", 10, "object[2].length", "at least the diameter"),
    ("obstacle.0.height", 0, "obstacle[1].height", "must be positive"),
    ("obstacle.0.polygon", [[0, 0], [1, 1], [1, 0], [0, 1]], "obstacle[1].polygon", "intersects itself"),
    ("tip", {"radius": -10}, "tip.radius", "must be positive"),
    ("tip", {"radius": 10, "colour": 1}, "tip.colour", "unknown key"),
    ("cantilever", {"Kn": 80}, "cantilever.Kn", "did you mean 'K_n'"),
    ("faults", {"stuck_object": 2}, "faults.stuck_object", "at most 1"),
    ("tipp", {"radius": 10}, "tipp", "did you mean 'tip'"),
]


@pytest.mark.parametrize("path,value,key,problem", CASES, ids=[c[0] + "=" + repr(c[1])[:20] for c in CASES])
def test_rejections(path, value, key, problem):
    with pytest.raises(InputError) as info:
        scene_from_dict(with_(path, value), "s.toml")
    line = str(info.value)
    assert line.startswith(f"s.toml: {key}"), line
    assert problem in line, line


def test_json_scene_file(tmp_path):
    s = scene_from_dict(base())
    s.save(tmp_path / "s.json")
    assert load_scene(tmp_path / "s.json") == s


@given(particles=st.integers(0, 40), rods=st.integers(0, 8), obstacles=st.integers(0, 3),
       seed=st.integers(0, 2**32 - 1))
def test_random_scenes_are_valid_and_round_trip(particles, rods, obstacles, seed):
    spec = SceneSpec(area=(8000.0, 6000.0), particles=particles, rods=rods, obstacles=obstacles,
                     obstacle_size=(200.0, 800.0))
    scene = random_scene(spec, seed)
    assert sum(o.kind == "particle" for o in scene.objects) == particles
    assert sum(o.kind == "rod" for o in scene.objects) == rods
    assert len(scene.obstacles) == obstacles
    # the loader accepts it again (no overlap, inside the area) and it round-trips exactly
    assert scene_from_dict(tomllib.loads(scene.dumps_toml())) == scene


def test_random_scene_is_deterministic_and_keeps_the_gap():
    spec = SceneSpec(particles=200, rods=20, obstacles=4, gap=80.0)
    a, b = random_scene(spec, 11), random_scene(spec, 11)
    assert a == b
    assert random_scene(spec, 12) != a
    from nanoasm.bodies import Body, overlapping_pairs
    grown = [Body(o.id, o.kind, o.at, o.diameter + 79.0, o.angle,
                  None if o.length is None else o.length + 79.0) for o in a.objects]
    assert overlapping_pairs(grown) == []


def test_random_scene_reports_when_objects_do_not_fit():
    with pytest.raises(InputError, match="--particles: only .* of 5000 particles fit"):
        random_scene(SceneSpec(area=(2000.0, 2000.0), particles=5000), 1)
    with pytest.raises(InputError, match="--rod-length"):
        random_scene(SceneSpec(rods=1, rod_length=(10.0, 20.0), rod_diameter=(50.0, 60.0)), 1)
