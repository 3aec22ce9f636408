"""World parameters: seed defaults, validated tables, exact round-trips, generated docs."""

from __future__ import annotations

import dataclasses
import math
import tomllib

import pytest
from nanoasm.fileio import dumps_toml
from hypothesis import given
from hypothesis import strategies as st

from nanoasm.errors import InputError
from nanoasm.world.limits import MIN_JUMP_EVERY
from nanoasm.schema import Table
from nanoasm.param import ParamError
from nanoasm.world.params import (
    TABLES,
    CantileverParams,
    DriftParams,
    TipParams,
    WorldParams,
    params_markdown,
)

SOURCE = "scene.toml"


def load(doc: dict) -> WorldParams:
    return WorldParams.from_tables({k: Table(v, SOURCE, k) for k, v in doc.items()})


def error_of(doc: dict) -> str:
    with pytest.raises(InputError) as e:
        load(doc)
    return str(e.value)


def groups():
    return [(name, type(getattr(WorldParams(), name))) for name in TABLES]


# -- defaults ----------------------------------------------------------------------------------------

def test_defaults_are_the_seed_numbers():
    w = WorldParams()
    c = w.cantilever
    assert (c.k, c.K_n, c.C1, c.C2, c.alpha, c.lateral_gain) == (0.12, 89.0, 1.3, 23.0, 0.18, 37.8)
    assert (c.length, c.tip_height, c.signal_limit) == (200000.0, 3000.0, 10.0)
    assert w.friction.mu_ts == 0.086 and w.friction.nu == 0.2
    assert w.adhesion.pull_off_fraction == 0.75
    assert w.scanner.xy_range == (90000.0, 90000.0) and w.scanner.z_range == 5000.0
    # C1 = K_n h / l (seed 3.6.3; the seed rounds 1.34 to 1.3)
    assert c.K_n * c.tip_height / c.length == pytest.approx(c.C1, abs=0.05)


def test_faults_are_off_by_default():
    f = WorldParams().faults
    assert f.stuck_object == f.tip_slip == f.lost_object == f.tip_blunting == 0.0


def test_default_drift_reaches_hundreds_of_nm_in_an_hour():
    d = WorldParams().drift
    steady = math.hypot(*d.velocity) * 3600
    walk = d.random_walk * math.sqrt(3600)
    assert 100 < steady < 1000 and 1 < walk < 50


def test_a_full_frame_takes_minutes():
    t = WorldParams().timing
    assert 2 * 60 < 512 * t.full_scan_line < 20 * 60


def test_every_field_is_documented():
    for name, cls in groups():
        for f in dataclasses.fields(cls):
            assert f.metadata.get("unit") and f.metadata.get("doc"), f"{name}.{f.name}"


# -- reading tables -------------------------------------------------------------------------------------

def test_no_tables_give_the_defaults():
    assert load({}) == WorldParams()


def test_given_keys_override_and_convert():
    w = load({"tip": {"radius": 25}, "scanner": {"dac_bits": 18, "nm_per_volt": [4000, 4000, 200]},
              "drift": {"velocity": [0, 0.1], "random_walk": 0}})
    assert w.tip == TipParams(radius=25.0)
    assert isinstance(w.tip.radius, float)
    assert w.scanner.dac_bits == 18 and w.scanner.nm_per_volt == (4000.0, 4000.0, 200.0)
    assert w.drift.velocity == (0.0, 0.1) and w.cantilever == CantileverParams()


@pytest.mark.parametrize("doc, message", [
    ({"cantilever": {"Kn": 90}}, "scene.toml: cantilever.Kn: unknown key (did you mean 'K_n'?)"),
    ({"tip": {"radius": -1}}, "scene.toml: tip.radius: must be positive, got -1"),
    ({"timing": {"push_speed": "fast"}}, "scene.toml: timing.push_speed: must be a number, got a string 'fast'"),
    ({"scanner": {"nm_per_volt": [1, 2]}}, "scene.toml: scanner.nm_per_volt: must be 3 numbers, got [1, 2]"),
    ({"scanner": {"nm_per_volt": [1, 2, -3]}}, "scene.toml: scanner.nm_per_volt: z must be positive, got -3"),
    ({"drift": {"velocity": [0.1, math.nan], "random_walk": 0}},
     "scene.toml: drift.velocity: y must be finite, got nan"),
    ({"drift": {"velocity": [0, 0]}}, "scene.toml: drift.random_walk: missing required key"),
    ({"noise": {}}, "scene.toml: noise.height_rms: missing required key"),
    ({"scanner": {"volt_range": [10, -10]}},
     "scene.toml: scanner.volt_range: low end must be below the high end, got [10, -10]"),
    ({"scanner": {"lift": 4000}}, "scene.toml: scanner.lift: must be below the top of the Z range (2500 nm)"),
    ({"scanner": {"dac_bits": 16.5}}, "scene.toml: scanner.dac_bits: must be an integer, got 16.5"),
    ({"faults": {"tip_slip": 1.5}}, "scene.toml: faults.tip_slip: must be at most 1, got 1.5"),
    ({"vdw": {"amplitude": True}}, "scene.toml: vdw.amplitude: must be a number, got a boolean True"),
    ({"tipp": {"radius": 3}}, "scene.toml: tipp: unknown table (world tables: tip, cantilever"),
])
def test_bad_input_is_one_located_line(doc, message):
    line = error_of(doc)
    assert line.startswith(message), line
    assert "\n" not in line


def test_direct_construction_is_validated_too():
    with pytest.raises(ParamError, match="radius: must be positive"):
        TipParams(radius=0)
    with pytest.raises(ParamError, match="half_angle: must be at most 80"):
        TipParams(half_angle=95)


def test_from_document_takes_only_world_tables():
    doc = Table({"format": "nanoasm.scene/1", "area": [10, 10], "object": [],
                 "creep": {"amplitude": 0.02}}, SOURCE)
    w = WorldParams.from_document(doc)
    assert w.creep.amplitude == 0.02 and w.tip == TipParams()


# -- writing tables ---------------------------------------------------------------------------------

def test_to_tables_writes_only_what_differs():
    assert WorldParams().to_tables() == {}
    w = dataclasses.replace(WorldParams(), tip=TipParams(radius=12))
    assert w.to_tables() == {"tip": {"radius": 12.0}}


def test_a_written_fixed_table_carries_its_required_keys():
    w = dataclasses.replace(WorldParams(), drift=DriftParams(random_walk=0.001))
    assert w.to_tables() == {"drift": {"velocity": [0.06, -0.04], "random_walk": 0.001}}


def _changed_value(f: dataclasses.Field, frac: float):
    """A valid non-default value for one field (kept inside every limit and cross-check)."""
    d, m = f.default, f.metadata
    if isinstance(d, int):
        return 8 + round(frac * 16)
    if isinstance(d, tuple):
        return tuple(v * (0.5 + 0.4 * frac) for v in d)
    if f.name == "jump_every":          # 0 or at least MIN_JUMP_EVERY
        return MIN_JUMP_EVERY * (1 + frac)
    if d == 0:
        return 0.5 * frac * (m["hi"] if m["hi"] is not None else 1.0)
    return d * (0.5 + 0.4 * frac)


@st.composite
def world_params(draw):
    w = WorldParams()
    for name, cls in groups():
        changes = {}
        for f in dataclasses.fields(cls):
            if f.name == "travel_speed":        # not read from a scene (nothing travels at it)
                continue
            if draw(st.booleans()):
                changes[f.name] = _changed_value(f, draw(st.floats(0, 1)))
        w = dataclasses.replace(w, **{name: cls(**changes)})
    return w


@given(world_params())
def test_round_trip_through_toml_is_exact(w):
    text = dumps_toml(w.to_tables())
    assert load(tomllib.loads(text)) == w


def test_markdown_lists_every_key_with_its_default():
    md = params_markdown()
    for name, cls in groups():
        assert f"### `[{name}]`" in md
        for f in dataclasses.fields(cls):
            assert f"| `{f.name}`" in md, f"{name}.{f.name}"
    assert "| `K_n` | 89 | nm/V |" in md
    assert "| `velocity` (required) | [0.06, -0.04] | nm/s |" in md
