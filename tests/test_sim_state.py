"""The simulated AFM's state as JSON (``state_dict`` / ``from_state``): a round trip is
exact, a world restored mid-push goes on bit for bit, and a state that is not what it
should be is refused naming its key (issue 15, item 1: a kept world is data, never code)."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import pickle
import re
import subprocess
import sys

import numpy as np
import pytest
import shapely
from simkit import particle, path_codes, preload_offset, rod, world

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.simkeep import SIM_FORMAT, load_sim_state, read_sim_state, sim_document, sim_state_path
from nanoasm.world.params import CreepParams, FaultParams, WorldParams
from nanoasm.world.scene import Scene
from nanoasm.world.sim import SimulatedAFM

#: Caches the drift model fills as it is asked (made again alike from its seed).
CACHES = {"_w", "_u", "_dirs", "_sums"}


def _busy_world() -> SimulatedAFM:
    """A particle, a rod and a wire; creep, van der Waals errors, noise and a blunting tip."""
    params = WorldParams(faults=FaultParams(tip_blunting=1.0), creep=CreepParams(min_step=50.0))
    wire = Body("w1", "rod", (2000.0, 2700.0), 40.0, 0.0, 1600.0)          # σ = 40: bends
    return world([particle((2000, 2000), d=60), rod((1000, 1200), 30.0, 400.0), wire], params=params, seed=7)


def _push_codes(sim: SimulatedAFM, start, end, *, lift: bool = True) -> np.ndarray:
    cfg = sim.config
    (x0, y0), (x1, y1) = np.asarray(start, float) - preload_offset(sim), np.asarray(end, float) - preload_offset(sim)
    points = [(x0, y0, cfg.lift), (x0, y0, -cfg.preload), (x1, y1, -cfg.preload)]
    return path_codes(sim, points + [(x1, y1, cfg.lift)] if lift else points)


def _json(state: dict) -> str:
    return json.dumps(state, allow_nan=False, sort_keys=True)


def _restored(sim: SimulatedAFM) -> SimulatedAFM:
    return SimulatedAFM.from_state(sim.scene, json.loads(_json(sim.state_dict())))


def _same(a, b, path: str = "sim", seen=None) -> None:
    """``a`` and ``b`` hold equal values all the way down (every attribute pickling kept)."""
    seen = set() if seen is None else seen
    if (id(a), id(b)) in seen:
        return
    seen.add((id(a), id(b)))
    if isinstance(a, np.random.Generator):
        assert a.bit_generator.state == b.bit_generator.state, path
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and np.array_equal(a, b), path
    elif isinstance(a, shapely.Geometry):
        assert shapely.equals_exact(a, b, 0.0), path
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path           # (an index: its order is not state)
        for k in a:
            _same(a[k], b[k], f"{path}[{k!r}]", seen)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for k, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{k}]", seen)
    elif isinstance(a, (set, frozenset)):
        assert sorted(a) == sorted(b), path
    elif hasattr(a, "__dict__") and not isinstance(a, type):
        assert type(a) is type(b), path
        for k, v in vars(a).items():
            if k not in CACHES:
                _same(v, vars(b)[k], f"{path}.{k}", seen)
    else:
        assert a == b, path


def _played(sim: SimulatedAFM, codes: np.ndarray):
    block = sim.write(codes)
    return block.t, block.s_n, block.s_l


def test_a_round_trip_through_json_is_exact():
    sim = _busy_world()
    off = _settled(sim, (2000.0, 2000.0))
    sim.write(_push_codes(sim, np.array((1700.0, 2000.0)) + off, np.array((2300.0, 2000.0)) + off))
    sim.write(_push_codes(sim, np.array((1500.0, 2400.0)) + off, np.array((1500.0, 2900.0)) + off))
    sim.scan_line((1000.0, 1000.0), (3000.0, 1000.0), 64)      # a move the creep records
    state = sim.state_dict()
    text = _json(state)
    again = SimulatedAFM.from_state(sim.scene, json.loads(text))
    assert _json(again.state_dict()) == text
    _same(sim, again)
    assert sim._drift.drift._moves_t and sim._world.pushes >= 2 and sim._world.blunted >= 2


def _settled(sim: SimulatedAFM, near) -> np.ndarray:
    """Bring the tip from its rest (tens of µm away) near ``near`` and let its creep die
    down over a full scan; returns where the sample then appears shifted (nm), to aim by."""
    sim.scan_line((near[0] - 400.0, near[1] - 400.0), (near[0] - 300.0, near[1] - 400.0), 8)
    sim.full_scan(256)
    return np.asarray(sim.true_offset(sim.clock() + 2.0))      # the push starts after a mode switch


def test_a_world_restored_mid_push_goes_on_bit_for_bit():
    sim = _busy_world()
    off = _settled(sim, (2000.0, 2000.0))
    codes = _push_codes(sim, np.array((1700.0, 2000.0)) + off, np.array((2300.0, 2000.0)) + off)
    k = 0
    while not sim._world.episodes:               # into the push, the particle on the tip
        sim.write(codes[k:k + 40])
        k += 40
    sim.write(codes[k:k + 200])
    k += 200
    assert sim._world.episodes and k < len(codes)
    again = _restored(sim)
    _same(sim, again)
    rest = {}
    for s in (sim, again):
        rest[id(s)] = [*_played(s, codes[k:]), s.scan_line((1500.0, 2000.0), (2500.0, 2000.0), 128),
                       *_played(s, _push_codes(s, (1500, 2400), (1500, 2900))), s.full_scan(32).height]
        s.park()
    for u, v in zip(rest[id(sim)], rest[id(again)]):
        assert np.array_equal(u, v)
    assert sim.truth() == again.truth() and sim.ledger() == again.ledger()
    assert _json(sim.state_dict()) == _json(again.state_dict())


def _bowtie_state():
    sim = _busy_world()
    off = _settled(sim, (2000.0, 2000.0))
    sim.write(_push_codes(sim, np.array((1700.0, 2000.0)) + off, np.array((1990.0, 2000.0)) + off,
                          lift=False))                                   # a push in progress
    return sim, sim.state_dict()


def _at(state: dict, path: str, value):
    bad = copy.deepcopy(state)
    keys = path.split(".")
    node = bad
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    last = keys[-1]
    if value is KeyError:
        del node[last]
    else:
        node[int(last) if isinstance(node, list) else last] = value
    return bad


@pytest.mark.parametrize("path, value, key", [
    ("format", "nanoasm.simworld/9", "format"),
    ("seed", 1.5, "seed"),
    ("seed", True, "seed"),
    ("placement", [0.0, math.nan], "placement"),
    ("clock.ns.push", -1, "clock.ns.push"),
    ("clock.ns", KeyError, "clock.ns"),
    ("rng.vdw.state.state", "123", "rng.vdw.state.state"),
    ("rng.scan.state.inc", 2 ** 130, "rng.scan.state.inc"),
    ("rng.signal.bit_generator", "MT19937", "rng.signal.bit_generator"),
    ("instrument.mode", "raster", "instrument.mode"),
    ("instrument.last", [1, 2, 70000], "instrument.last[3]"),
    ("tip.z", math.inf, "tip.z"),
    ("drift.moves_s", [[1.0]], "drift.moves_s"),
    ("units.a", [[0.0, 0.0]], "units.a"),
    ("units.centre.0.1", "2000", "units.centre"),
    ("units.angle.0", 12.0, "units.angle[1]"),
    ("units.at.1.0", 1e400, "units.at"),
    ("wires", [], "wires"),
    ("wires.0.nodes", [[0.0, 0.0]], "wires[1].nodes"),
    ("episodes.0.mode", "fly", "episodes[1].mode"),
    ("episodes.0.branch", 0, "episodes[1].branch"),
    ("episodes.0.moved", [10 ** 6], "episodes[1].moved[1]"),
    ("params.creep.min_step", "far", "params.creep.min_step"),
    ("params.faults", [], "params.faults"),
    ("world.tip_radius", 0.0, "world.tip_radius"),
    ("extra", 1, "extra"),
])
def test_a_bad_field_is_refused_naming_its_key(path, value, key):
    sim, state = _bowtie_state()
    assert state["episodes"], "the push should be in progress"
    with pytest.raises(ValueError, match="^" + re.escape(key) + ": "):
        SimulatedAFM.from_state(sim.scene, _at(state, path, value))


def test_a_state_of_another_scene_is_refused():
    sim, state = _bowtie_state()
    moved = dataclasses.replace(sim.scene.objects[0], at=(2001.0, 2000.0))
    other = Scene(sim.scene.area, (moved, *sim.scene.objects[1:]), (), sim.scene.params, sim.scene.seed)
    with pytest.raises(ValueError, match="^scene_sha256: the world kept is of another scene"):
        SimulatedAFM.from_state(other, state)
    # the same scene written with whole numbers is the same scene
    ints = Scene((4000, 4000), sim.scene.objects, (), sim.scene.params, sim.scene.seed)
    assert SimulatedAFM.from_state(ints, state).truth() == sim.truth()


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_kept_file_is_json_and_a_crafted_one_runs_nothing(tmp_path):
    sim, state = _bowtie_state()
    doc = sim_document(12.5, sim, 0.0, sim.scene.objects)
    good = tmp_path / "run.mcap.sim"
    good.write_text(json.dumps(doc, allow_nan=False))
    kept = load_sim_state(good, sim.scene)
    assert kept["t"] == 12.5 and kept["initial"] == sim.scene.objects and kept["sim"].truth() == sim.truth()
    marker = tmp_path / "ran"
    cases = {
        "a pickle, which nanoasm no longer opens": pickle.dumps(_Evil(marker)),
        "not JSON": json.dumps({**doc, "t": math.nan}).encode(),
        "not a nanoasm simulated world": json.dumps({**doc, "format": "nanoasm.simstate/1"}).encode(),
        "world: tip.force: must be an array of two numbers": json.dumps(_at(doc, "world.tip.force", None)).encode(),
        "world: scene_sha256": json.dumps(_at(doc, "world.scene_sha256", "x")).encode(),
        "initial: the objects at the start are not the log's": json.dumps({**doc, "initial": []}).encode(),
        "initial[1].diameter": json.dumps(_at(doc, "initial.0.diameter", -1)).encode(),
        "unreadable": b"{" * 100000,
    }
    for text, data in cases.items():
        bad = tmp_path / "bad.sim"
        bad.write_bytes(data)
        with pytest.raises(InputError) as err:
            load_sim_state(bad, sim.scene)
        line = str(err.value)
        assert "\n" not in line and line.startswith(f"{bad}: ") and text in line, line
    assert not marker.exists()
    assert doc["format"] == SIM_FORMAT and read_sim_state(good)["world"] == json.loads(json.dumps(state))


def test_a_crafted_sim_file_runs_nothing(tmp_path):
    """A pickle that would call os.system, beside a log of random bytes (issue 15, item 1):
    one line naming the file, exit 1, and nothing ran."""
    marker = tmp_path / "ran"
    log = tmp_path / "run.mcap"
    log.write_bytes(os.urandom(4096))
    sim_state_path(log).write_bytes(pickle.dumps(_Evil(marker)))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    for body, text in ((None, "a pickle, which nanoasm no longer opens"),
                       (b'{"format": "nanoasm.simstate/2", "t": NaN}', "not JSON"),
                       (b'{"format": "nanoasm.simstate/2", "t": 1.0}', "start_clock: missing")):
        if body is not None:
            sim_state_path(log).write_bytes(body)
        done = subprocess.run([sys.executable, "-m", "nanoasm.cli", "dry-run", "--resume", str(log)], cwd=tmp_path,
                              capture_output=True, text=True, timeout=120, env=env)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 1 and len(lines) == 1, done.stderr
        assert str(sim_state_path(log)) in lines[0] and text in lines[0], lines[0]
        assert not marker.exists()
