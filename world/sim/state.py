"""The simulated AFM's state as plain JSON: written at a checkpoint, checked, read back.

A dry-run keeps its world beside its log to resume it (:mod:`nanoasm.simkeep`). The world
is its parameters and seed, where the scene's objects are now (every contact unit's pose,
every wire's nodes), the pushes in progress, the instrument's clock, tip, DAC and mode,
the creep's recorded moves and the states of the random generators still in use.
:func:`sim_state` gives them as JSON types (numbers, strings, arrays, tables);
:func:`sim_from_state` builds the instrument anew from the scene and the seed (what only
they decide: the objects' own constants, the substrate, the drift's noise, made exactly
as at the start) and then reads the rest back, every field checked (type, shape, finite
numbers, ranges); a bad one raises :class:`ValueError` naming its key. The state names
its scene by a digest (:func:`scene_digest`): a state of another scene is refused.
Reading a state runs nothing from it. Units: nm, degrees, seconds (the clock in integer ns).
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.param import show_value
from nanoasm.schema import Table
from nanoasm.world.params import WorldParams

from .afm import TAPPING, CONTACT, SimulatedAFM
from .clock import ACTIVITIES
from .faults import PushFaults
from .push import GONE, PUSH, RIDE, Episode
from .stream import TipState

STATE_FORMAT = "nanoasm.simworld/1"
#: The random streams a simulated AFM draws from after it is built (the others, for the
#: objects' truth, the drift's seed and the substrate, are spent at the start).
KEPT_STREAMS = ("faults", "vdw", "scan", "signal")
_KEYS = ("format", "scene_sha256", "params", "seed", "placement", "clock", "rng", "instrument", "tip",
         "drift", "moves", "world", "units", "wires", "episodes")


def scene_digest(scene) -> str:
    """SHA-256 of the scene's document (numbers as floats: a file's 100 is a program's 100.0)."""
    text = json.dumps(_floats_only(scene.to_dict()), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _floats_only(x):
    if isinstance(x, dict):
        return {k: _floats_only(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_floats_only(v) for v in x]
    if isinstance(x, int) and not isinstance(x, bool):
        return float(x)
    return x


def _streams(sim: SimulatedAFM) -> dict[str, np.random.Generator]:
    return {"faults": sim._world.rng_faults, "vdw": sim._world.rng_vdw, "scan": sim._rng_scan,
            "signal": sim._rng_signal}


def _xy(v) -> list[float]:
    return [float(v[0]), float(v[1])]


def _opt(v) -> float | None:
    return None if v is None else float(v)


# -- writing ---------------------------------------------------------------------------------------
def sim_state(sim: SimulatedAFM) -> dict:
    """The state of ``sim`` as JSON types (see the module docstring)."""
    w, c, tip, dm = sim._world, sim._world.contacts, sim._state, sim._drift.drift
    units = c.bodies
    return {
        "format": STATE_FORMAT,
        "scene_sha256": scene_digest(sim.scene),
        "params": json.loads(json.dumps(sim.params.to_tables())),   # tuples as arrays
        "seed": int(sim.seed),
        "placement": _xy(sim.placement),
        "clock": {"start_ns": int(sim._clock._start_ns), "ns": {a: int(v) for a, v in sim._clock._ns.items()}},
        "rng": {name: g.bit_generator.state for name, g in _streams(sim).items()},
        "instrument": {"mode": sim._mode, "last": [int(v) for v in sim._last],
                       **({} if sim.first_scan is None else {"first_scan": [float(v) for v in sim.first_scan]}),
                       "piezo_xy": None if sim._piezo_xy is None else _xy(sim._piezo_xy),
                       "signals": _xy(sim._signals)},
        "tip": {"piezo": _xy(tip.piezo), "tip": _xy(tip.tip), "z": float(tip.z), "sl_bar": float(tip.sl_bar),
                "ride": float(tip.ride), "motion": _xy(tip.motion), "force": _xy(tip.force)},
        "drift": {"epoch": float(dm.epoch), "moves_t": [float(v) for v in dm._moves_t],
                  "moves_s": [_xy(s) for s in dm._moves_s]},
        "moves": {"start": _xy(sim._moves.start), "still": int(sim._moves.still),
                  **({} if sim._moves.rest is None else
                     {"rest": [float(sim._moves.rest[0]), float(sim._moves.rest[1]), *_xy(sim._moves.rest[2])]})},
        "world": {"tip_radius": float(w.tip_radius), "lag": _xy(w.lag), "version": int(w.version),
                  "pushes": int(w.pushes), "slips": int(w.slips), "blunted": int(w.blunted),
                  "steps": int(w.steps), "pair_tests": int(c.pair_tests)},
        "units": {"at": [_xy(b.at) for b in units], "angle": [_opt(b.angle) for b in units],
                  "length": [_opt(b.length) for b in units], "a": c._a.tolist(), "b": c._b.tolist(),
                  "centre": c._centre.tolist()},
        "wires": [{"object": int(o), "nodes": nodes.tolist()} for o, nodes in w.wires.items()],
        "episodes": [{"object": int(o), **_episode(ep)} for o, ep in w.episodes.items()],
    }


def _episode(ep: Episode) -> dict:
    f = ep.faults
    return {"mode": ep.mode, "theta": float(ep.theta), "f_push": float(ep.f_push), "f_fric": float(ep.f_fric),
            "branch": int(ep.branch),
            "travelled": float(ep.travelled), "moved": sorted(int(u) for u in ep.moved),
            "heading": None if ep.heading is None else _xy(ep.heading),
            "trail": None if ep.trail is None else _xy(ep.trail),
            "faults": {"stuck": bool(f.stuck), "lost": bool(f.lost), "blunt": bool(f.blunt),
                       "slip_after": None if math.isinf(f.slip_after) else float(f.slip_after),
                       "jump": _xy(f.jump)}}


# -- reading ---------------------------------------------------------------------------------------
def sim_from_state(scene, state) -> SimulatedAFM:
    """The simulated AFM over ``scene`` as :func:`sim_state` saw it; ``ValueError`` naming the
    key of a field that is missing, of the wrong type or shape, not finite or out of range,
    or when the state is of another scene."""
    try:
        return _restore(scene, Table(state, None))
    except InputError as err:
        raise ValueError(err.line()) from None


def _restore(scene, t: Table) -> SimulatedAFM:
    t.check_keys(required=_KEYS)
    if t.string("format") != STATE_FORMAT:
        t.fail("format", f"must be {STATE_FORMAT!r}, got {show_value(t.data['format'])}")
    if t.string("scene_sha256") != scene_digest(scene):
        t.fail("scene_sha256", "the world kept is of another scene than the log's")
    ptab = t.table("params")
    params = WorldParams.from_tables({name: ptab.table(name) for name in ptab.data})
    clock = _table(t, "clock", "start_ns", "ns")
    start_ns = clock.integer("start_ns", nonnegative=True)
    try:
        sim = SimulatedAFM(scene, seed=_uint(t, "seed"), params=params, placement=t.pair("placement"),
                           start_time=start_ns / 1e9)
    except ValueError as err:
        t.fail("params", str(err))
    ns = _table(clock, "ns", *ACTIVITIES)
    sim._clock._start_ns = start_ns
    sim._clock._ns = {a: ns.integer(a, nonnegative=True) for a in ACTIVITIES}
    rng = _table(t, "rng", *KEPT_STREAMS)
    for name, gen in _streams(sim).items():
        gen.bit_generator.state = _rng_state(rng.table(name))
    _instrument(sim, t)
    _world(sim, t)
    return sim


def _instrument(sim: SimulatedAFM, t: Table) -> None:
    """The DAC, the mode, the tip and the creep's moves."""
    ins = t.table("instrument")
    ins.check_keys(required=("mode", "last", "piezo_xy", "signals"), optional=("first_scan",))
    if "first_scan" in ins.data:                 # absent: none yet, or an older state
        f = _floats(ins, "first_scan", (5,))
        sim.first_scan = (float(f[0]), float(f[1]), float(f[2]), float(f[3]), int(f[4]))
    sim._mode = ins.string("mode", choices=(TAPPING, CONTACT))
    last = ins.array("last", min_len=3, max_len=3)
    sim._last = np.array([_code(ins, f"last[{k + 1}]", v, sim.config.max_code) for k, v in enumerate(last)],
                         dtype=np.int64)
    sim._piezo_xy = None if ins.is_null("piezo_xy") else np.array(ins.pair("piezo_xy"))
    sim._signals = ins.pair("signals")
    tip = t.table("tip")
    tip.check_keys(required=("piezo", "tip", "z", "sl_bar", "ride", "motion"), optional=("force", "f_lat"))
    motion = np.array(tip.pair("motion"))
    # the lateral force on the tip; a state kept before it was a vector held its size against the motion
    force = np.array(tip.pair("force")) if "force" in tip.data else -tip.number("f_lat") * motion
    sim._state = TipState(np.array(tip.pair("piezo")), tip.pair("tip"), tip.number("z"),
                          tip.number("sl_bar"), tip.number("ride"), motion, force)
    drift = _table(t, "drift", "epoch", "moves_t", "moves_s")
    dm = sim._drift.drift
    dm.epoch = drift.number("epoch")
    times = _floats(drift, "moves_t", (None,))
    steps = _floats(drift, "moves_s", (len(times), 2))
    dm.set_moves(times, steps)
    moves = t.table("moves")
    moves.check_keys(required=("start", "still"), optional=("rest",))
    sim._moves.start = np.array(moves.pair("start"))
    sim._moves.still = moves.integer("still", nonnegative=True)
    rest = _floats(moves, "rest", (4,)) if "rest" in moves.data else None     # absent: none open, or an older state
    sim._moves.rest = None if rest is None else (float(rest[0]), float(rest[1]), np.asarray(rest[2:], float))


def _world(sim: SimulatedAFM, t: Table) -> None:
    """The objects where they are now and the pushes in progress."""
    w, c = sim._world, sim._world.contacts
    wt = _table(t, "world", "tip_radius", "lag", "version", "pushes", "slips", "blunted", "steps",
                "pair_tests")
    w.tip_radius = wt.number("tip_radius", positive=True)
    w.lag = wt.pair("lag")
    w.version = wt.integer("version", nonnegative=True)
    w.pushes, w.slips, w.blunted, w.steps = (wt.integer(k, nonnegative=True)
                                             for k in ("pushes", "slips", "blunted", "steps"))
    c.pair_tests = wt.integer("pair_tests", nonnegative=True)
    ut = _table(t, "units", "at", "angle", "length", "a", "b", "centre")
    n = len(c)
    at = _floats(ut, "at", (n, 2))
    angle, length = _optional_floats(ut, "angle", n), _optional_floats(ut, "length", n)
    bodies = []
    for i, old in enumerate(c.bodies):
        try:
            bodies.append(Body(old.id, old.kind, (float(at[i, 0]), float(at[i, 1])), old.diameter,
                               angle[i], length[i]))
        except ValueError as err:
            ut.fail(f"angle[{i + 1}]", f"unit {old.id}: {err}")
    arrays = {k: _floats(ut, k, (n, 2)) for k in ("a", "b", "centre")}
    c._bodies = bodies
    c._a[:], c._b[:], c._centre[:] = arrays["a"], arrays["b"], arrays["centre"]
    for i in range(n):
        c._index(i)
    wires = t.tables("wires")
    if sorted(_wire_object(x, w.wires) for x in wires) != sorted(w.wires):
        t.fail("wires", f"must hold the nodes of every wire of the scene once ({len(w.wires)})")
    for x in wires:
        o = x.integer("object")
        w.wires[o] = _floats(x, "nodes", w.wires[o].shape)
    w.episodes = {}
    for x in t.tables("episodes"):
        o = x.integer("object", lo=0, hi=len(w.table) - 1)
        if o in w.episodes:
            x.fail("object", f"a second push of object {o} in progress")
        w.episodes[o] = _read_episode(x, n)


def _wire_object(x: Table, wires: dict) -> int:
    x.check_keys(required=("object", "nodes"))
    o = x.integer("object")
    if o not in wires:
        x.fail("object", f"object {o} is no wire of the scene")
    return o


def _read_episode(x: Table, n_units: int) -> Episode:
    x.check_keys(required=("object", "mode", "theta", "f_push", "branch", "travelled", "moved", "heading",
                           "trail", "faults"), optional=("f_fric",))
    f = _table(x, "faults", "stuck", "lost", "blunt", "slip_after", "jump")
    faults = PushFaults(stuck=f.boolean("stuck"),
                        slip_after=math.inf if f.is_null("slip_after") else f.number("slip_after", nonnegative=True),
                        lost=f.boolean("lost"), blunt=f.boolean("blunt"), jump=f.pair("jump"))
    branch = x.integer("branch")
    if branch not in (-1, 1):
        x.fail("branch", f"must be -1 or 1, got {branch}")
    moved = {_code(x, f"moved[{k + 1}]", v, n_units - 1) for k, v in enumerate(x.array("moved"))}
    return Episode(x.string("mode", choices=(PUSH, RIDE, GONE)), faults, x.number("theta"),
                   x.number("f_push"), 0.0 if "f_fric" not in x.data else x.number("f_fric", nonnegative=True),
                   branch, x.number("travelled", nonnegative=True), moved,
                   None if x.is_null("heading") else x.pair("heading"),
                   None if x.is_null("trail") else x.pair("trail"))


# -- checked fields --------------------------------------------------------------------------------
def _table(t: Table, name: str, *keys: str) -> Table:
    sub = t.table(name)
    sub.check_keys(required=keys)
    return sub


def _uint(t: Table, name: str, bits: int | None = None) -> int:
    """A non-negative integer, below ``2**bits`` if given (a seed or a generator's state)."""
    v = t.data.get(name)
    if type(v) is not int or v < 0 or (bits is not None and v >= 2 ** bits):
        below = f" below 2**{bits}" if bits is not None else ""
        t.fail(name, f"must be a non-negative integer{below}, got {show_value(v)}")
    return v


def _code(t: Table, key: str, v, top: int) -> int:
    if type(v) is not int or not 0 <= v <= top:
        t.fail(key, f"must be an integer from 0 to {top}, got {show_value(v)}")
    return v


def _rng_state(t: Table) -> dict:
    """A PCG64 generator's state (numpy's ``bit_generator.state``), checked."""
    t.check_keys(required=("bit_generator", "state", "has_uint32", "uinteger"))
    t.string("bit_generator", choices=("PCG64",))
    s = _table(t, "state", "state", "inc")
    return {"bit_generator": "PCG64", "state": {"state": _uint(s, "state", 128), "inc": _uint(s, "inc", 128)},
            "has_uint32": _uint(t, "has_uint32", 1), "uinteger": _uint(t, "uinteger", 32)}


def _floats(t: Table, name: str, shape: tuple) -> np.ndarray:
    """An array of finite numbers of ``shape`` (``None``: any length)."""
    value = t.array(name)
    want = "x".join("n" if s is None else str(s) for s in shape)
    bad = f"must be an array of {want} finite numbers"
    stack = [(value, 0)]
    while stack:                     # numbers, and nothing else, at the array's depth
        v, depth = stack.pop()
        if depth == len(shape):
            if type(v) not in (int, float):
                t.fail(name, f"{bad}, holds {show_value(v)}")
        elif not isinstance(v, list) or (shape[depth] is not None and len(v) != shape[depth]):
            t.fail(name, f"{bad}")
        else:
            stack.extend((x, depth + 1) for x in v)
    try:                             # rectangular now: only the first length is free
        arr = np.array(value, dtype=float).reshape(tuple(len(value) if s is None else s for s in shape))
    except (ValueError, OverflowError):
        t.fail(name, bad)
    if not np.all(np.isfinite(arr)):
        t.fail(name, f"{bad}, holds one not finite")
    return arr


def _optional_floats(t: Table, name: str, n: int) -> list[float | None]:
    """``n`` entries, each a finite number or null."""
    value = t.array(name, min_len=n, max_len=n)
    out = []
    for k, v in enumerate(value):
        if v is not None and (type(v) not in (int, float) or not math.isfinite(v)):
            t.fail(f"{name}[{k + 1}]", f"must be a finite number or null, got {show_value(v)}")
        out.append(None if v is None else float(v))
    return out
