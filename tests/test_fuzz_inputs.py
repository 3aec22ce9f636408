"""Whatever a user's file holds, loading it either succeeds or raises InputError."""

from __future__ import annotations

import copy
import json

from hypothesis import HealthCheck, given, settings, strategies as st

from nanoasm.cad.layout import layout_from_dict
from nanoasm.errors import InputError
from nanoasm.executor.report import report_from_dict
from nanoasm.fileio import parse_json, parse_toml
from nanoasm.planner.plan import plan_from_dict
from nanoasm.world.environment import environment_from_dict
from nanoasm.world.scene import scene_from_dict

from pathlib import Path

GOLDEN = Path(__file__).parent / "golden"

LAYOUT = {
    "format": "nanoasm.layout/1", "area": [5000, 5000], "tolerance": {"position": 20},
    "target": [{"kind": "particle", "at": [1000, 1000], "diameter": 100},
               {"kind": "rod", "at": [2500, 2500], "angle": 30, "length": 1300, "diameter": 100}],
    "keepout": [{"polygon": [[0, 4000], [800, 4000], [800, 4400], [0, 4400]]}],
}
SCENE = {
    "format": "nanoasm.scene/1", "area": [10000, 10000], "seed": 1,
    "object": [{"kind": "particle", "at": [3000, 4000], "diameter": 100},
               {"kind": "rod", "at": [6000, 6000], "angle": 75, "length": 1300, "diameter": 100}],
    "obstacle": [{"polygon": [[100, 100], [600, 100], [600, 300]], "height": 30}],
    "drift": {"velocity": [0.1, 0.1], "random_walk": 0.05}, "noise": {"height_rms": 0.3},
}

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.integers(10**300, 10**400),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8))
values = st.recursive(scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=3),
                      max_leaves=8)


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, prefix + (i,))


def _mutate(doc, data):
    doc = copy.deepcopy(doc)
    paths = [p for p in _paths(doc) if p]
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        node = doc
        try:
            for k in path[:-1]:
                node = node[k]
            action = data.draw(st.sampled_from(["replace", "delete", "add"]))
            if action == "replace":
                node[path[-1]] = data.draw(values)
            elif action == "delete":
                del node[path[-1]]
            elif isinstance(node, dict):
                node[data.draw(st.text(max_size=6))] = data.draw(values)
        except (KeyError, IndexError, TypeError):
            pass
    return doc


def _check(loader, doc):
    try:
        loader(doc, "f.toml")
    except InputError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("f.toml: ")


@settings(suppress_health_check=[HealthCheck.too_slow], max_examples=300)
@given(st.data())
def test_mutated_layouts_and_scenes(data):
    _check(layout_from_dict, _mutate(LAYOUT, data))
    _check(scene_from_dict, _mutate(SCENE, data))


@settings(suppress_health_check=[HealthCheck.too_slow], max_examples=200)
@given(st.data())
def test_mutated_env_plan_report(data):
    for name, loader in (("env.json", environment_from_dict), ("plan.json", plan_from_dict),
                         ("report.json", report_from_dict)):
        _check(loader, _mutate(json.loads((GOLDEN / name).read_text()), data))


@given(st.binary(max_size=200) | st.text(max_size=200))
def test_arbitrary_text_parses_or_fails_cleanly(blob):
    text = blob.decode("latin-1") if isinstance(blob, bytes) else blob
    for parse in (parse_json, parse_toml):
        try:
            parse(text, "f")
        except InputError:
            pass
