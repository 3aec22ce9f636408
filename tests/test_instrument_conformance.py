"""What the Instrument protocol (nanoasm/instrument/protocol.py) promises, checked alike on
every implementation: the simulated AFM, the NI-DAQmx backend through its fake driver
(tests/nidaqmx_fake.py) and the Nanonis backend through its fake controller
(tests/nanonis_fake.py).

- a command beyond the limits raises InstrumentLimitError before anything is sent;
- every exit of a run parks: Z at the top of its range, XY at rest, as the hardware
  itself (not only the backend's belief) shows; park is safe from any state, repeatedly;
- a full scan is a HeightImage in the scanner frame (a feature at a known scanner
  position is imaged there), a scan line's heights run from a to b, and both end lifted;
- instrument time is monotonic, and a chunk's sample times lie within the write.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
from nidaqmx_fake import FakeNidaqmx
from simkit import particle, world

from nanoasm.errors import InstrumentLimitError
from nanoasm.examples import path as example_path
from nanoasm.executor.engine import Msg, RunEngine
from nanoasm.executor.instrument_file import instrument_from_dict
from nanoasm.executor.nidaq import NiDaqInstrument
from nanoasm.instrument import HeightImage, Instrument, SignalBlock, ramp

#: A feature at this scanner-frame point (nm) in every world: a 150 nm particle in the
#: simulator, a 40 nm Gaussian bump (σ = 300 nm) in the fakes.
FEATURE = np.array([2000.0, 2000.0])
REGION = (1000.0, 1000.0, 3000.0, 3000.0)


def bump(x, y):
    """Height (nm) of the fakes' feature at scanner-frame ``x``, ``y`` (nm)."""
    return 40.0 * np.exp(-((x - FEATURE[0]) ** 2 + (y - FEATURE[1]) ** 2) / (2 * 300.0 ** 2))


@dataclass
class Backend:
    """An open instrument and what its hardware shows, independently of the backend."""

    inst: Instrument
    sent: Callable[[], object]          # a snapshot of everything sent; unchanged: nothing was sent
    at_rest: Callable[[], bool]         # the hardware's own state is parked
    close: Callable[[], None]


def sim_backend() -> Backend:
    inst = world([particle(FEATURE, d=150.0)], area=(4000.0, 4000.0))
    rest = inst.config.rest_codes()
    return Backend(inst, lambda: (inst.clock(), tuple(inst.position()), inst.signals()),
                   lambda: np.array_equal(inst.position(), rest), lambda: None)


def ni_backend() -> Backend:
    f = instrument_from_dict(tomllib.loads(example_path("instrument_ni.toml").read_text()), "ni.toml")
    cfg = f.scanner

    def signal(volts, index):
        nm = cfg.volts_to_nm(volts.T)
        s_n = np.maximum(0.0, -nm[:, 2]) / 89.0          # deflection below the surface, K_n = 89 nm/V
        return np.vstack([s_n, 1e-3 * nm[:, 0], bump(nm[:, 0], nm[:, 1]) / f.imaging.height_nm_per_volt])

    fake = FakeNidaqmx(signal)
    inst = NiDaqInstrument(f, nidaqmx_module=fake)
    rest = cfg.rest_codes()

    def at_rest():      # the DAC holds the last sample played; before any, the rest it starts at
        played = fake.played_volts()
        return played.shape[0] == 0 or np.array_equal(cfg.volts_to_codes(played[-1]), rest)

    return Backend(inst, lambda: (len(fake.writes), len(fake.played)), at_rest, inst.close)


def nanonis_backend() -> Backend:
    pytest.importorskip("nanonis_spm")
    from nanonis_fake import FakeNanonis

    from nanoasm.executor.nanonis import NanonisInstrument

    doc = tomllib.loads(example_path("instrument_nanonis.toml").read_text())
    half = np.asarray(doc["scanner"]["xy_range"], float) / 2
    surface = 1e-6

    def height(x, y):                                   # Nanonis metres: scanner nm = m * 1e9 + half
        return surface + 1e-9 * float(bump(x * 1e9 + half[0], y * 1e9 + half[1]))

    fake = FakeNanonis(surface=height)
    doc["nanonis"].update(port=fake.port, scan_channel=3)
    doc["imaging"]["settle"] = 0.0
    inst = NanonisInstrument(instrument_from_dict(doc, "nanonis.toml"))
    cfg = inst.config
    rest = cfg.codes_to_nm(cfg.rest_codes())

    def at_rest():
        top = surface + cfg.z_range / 2 * 1e-9
        xy = (rest[:2] - half) * 1e-9
        return (not fake.on and math.isclose(fake.z, top, abs_tol=1e-10)
                and np.allclose((fake.x, fake.y), xy, atol=1e-12) and not fake.violations)

    def close():
        inst.close()
        fake.close()

    return Backend(inst, lambda: len(fake.calls), at_rest, close)


@pytest.fixture(params=["sim", "nidaq", "nanonis"])
def backend(request):
    b = {"sim": sim_backend, "nidaq": ni_backend, "nanonis": nanonis_backend}[request.param]()
    try:
        yield b
    finally:
        b.close()


def pressed_path(inst: Instrument, depth: float = 50.0, push: float = 300.0) -> np.ndarray:
    """From the present output: lifted travel to 500 nm left of the feature, lower to
    ``-depth`` nm, push ``push`` nm in x, all within the slew limit (ends pressed)."""
    cfg = inst.config
    here = inst.position()
    a = cfg.nm_to_codes(np.array([FEATURE[0] - 500.0, FEATURE[1] - 800.0, cfg.lift]))
    b = a.copy()
    b[2] = cfg.nm_to_codes(np.array([0.0, 0.0, -depth]))[2]
    c = cfg.nm_to_codes(cfg.codes_to_nm(b) + [push, 0.0, 0.0])
    up = here.copy()
    up[2] = max(up[2], a[2])
    return np.vstack([ramp(here, up, cfg), ramp(up, a, cfg), ramp(a, b, cfg), ramp(b, c, cfg, speed=2000.0)])


def lift_code(cfg) -> int:
    return int(cfg.nm_to_codes(np.array([0.0, 0.0, cfg.lift]))[2])


# -- limits ----------------------------------------------------------------------------------------

def test_every_implementation_is_an_instrument(backend):
    assert isinstance(backend.inst, Instrument)


def fast(cfg, axis: int) -> int:
    """Codes along ``axis`` of one step three times the slew limit's."""
    return math.ceil(3 * cfg.max_step / cfg.nm_per_code[axis])


BAD_CHUNKS = {
    "NaN": lambda cfg, p: np.array([[np.nan, p[1], p[2]]]),
    "infinite": lambda cfg, p: np.array([[p[0], np.inf, p[2]]]),
    "not an integer": lambda cfg, p: np.array([[p[0] + 0.5, p[1], p[2]]]),
    "below the DAC range": lambda cfg, p: np.array([[-1, p[1], p[2]]]),
    "above the DAC range": lambda cfg, p: np.array([[p[0], p[1], cfg.max_code + 1]]),
    "too fast from the present output": lambda cfg, p: np.array([[p[0] + fast(cfg, 0), p[1], p[2]]]),
    "too fast within the chunk": lambda cfg, p: np.array([p, p, [p[0], p[1] - fast(cfg, 1), p[2]]]),
    "a step too fast in Z": lambda cfg, p: np.array([p, [p[0], p[1], p[2] - fast(cfg, 2)]]),
    "not (n, 3)": lambda cfg, p: np.array([p[:2]]),
    "empty": lambda cfg, p: np.empty((0, 3), np.int64),
}


@pytest.mark.parametrize("bad", list(BAD_CHUNKS))
def test_a_chunk_beyond_the_limits_is_refused_before_anything_is_sent(backend, bad):
    inst = backend.inst
    here = inst.position()
    before = backend.sent()
    with pytest.raises(InstrumentLimitError):
        inst.write(BAD_CHUNKS[bad](inst.config, here))
    assert backend.sent() == before
    np.testing.assert_array_equal(inst.position(), here)


@pytest.mark.parametrize("call", [
    lambda i: i.scan_line((-10.0, 500.0), (500.0, 500.0), 8),
    lambda i: i.scan_line((500.0, 500.0), (500.0, i.config.xy_range[1] + 1.0), 8),
    lambda i: i.full_scan(16, (-100.0, 0.0, 1000.0, 1000.0)),
    lambda i: i.full_scan(16, (0.0, 0.0, 1000.0, i.config.xy_range[1] + 500.0)),
    lambda i: i.full_scan(16, (i.config.xy_range[0] - 1000.0, 0.0, i.config.xy_range[0], 5000.0)),
], ids=["line start", "line end", "region corner", "region beyond the range", "square beyond the range"])
def test_a_scan_beyond_the_range_is_refused_before_anything_is_sent(backend, call):
    before = backend.sent()
    here = backend.inst.position()
    with pytest.raises(InstrumentLimitError):
        call(backend.inst)
    assert backend.sent() == before
    np.testing.assert_array_equal(backend.inst.position(), here)


# -- parking ---------------------------------------------------------------------------------------------

class Boom(Exception):
    pass


@pytest.mark.parametrize("ending", ["completes", "raises", "Ctrl-C"])
def test_every_exit_of_a_run_parks_the_hardware(backend, ending):
    inst = backend.inst

    def procedure():
        here = yield Msg("position")
        assert np.array_equal(here, inst.position())
        yield Msg("scan_line", ((500.0, 500.0), (900.0, 500.0), 8))
        block = yield Msg("write", (pressed_path(inst),))
        assert isinstance(block, SignalBlock)
        assert not backend.at_rest()
        if ending == "raises":
            raise Boom("the procedure failed")
        if ending == "Ctrl-C":
            raise KeyboardInterrupt
        return "done"

    engine = RunEngine(inst)
    if ending == "completes":
        assert engine.run(procedure()) == "done"
    else:
        with pytest.raises(Boom if ending == "raises" else KeyboardInterrupt):
            engine.run(procedure())
    assert backend.at_rest()
    np.testing.assert_array_equal(inst.position(), inst.config.rest_codes())


def test_park_is_safe_from_any_state_and_repeatedly(backend):
    inst = backend.inst
    rest = inst.config.rest_codes()
    for before_park in (lambda: None, lambda: inst.write(pressed_path(inst)),
                        lambda: inst.scan_line((500.0, 500.0), (900.0, 700.0), 8),
                        lambda: inst.full_scan(16, (500.0, 500.0, 1500.0, 1500.0))):
        before_park()
        inst.park()
        inst.park()
        assert backend.at_rest()
        np.testing.assert_array_equal(inst.position(), rest)


# -- scans -------------------------------------------------------------------------------------------------

def test_a_full_scan_is_a_height_image_in_the_scanner_frame(backend):
    inst = backend.inst
    image = inst.full_scan(32, REGION)
    assert isinstance(image, HeightImage)
    assert image.shape == (32, 32) and image.pixel_size == pytest.approx(2000.0 / 32)
    assert image.origin == pytest.approx(REGION[:2])
    i, j = np.unravel_index(np.nanargmax(image.height), image.shape)
    xs, ys = image.pixel_centres()
    assert math.dist((xs[j], ys[i]), FEATURE) <= 1.5 * image.pixel_size
    assert np.nanmax(image.height) - np.nanpercentile(image.height, 10) > 30.0
    assert inst.position()[2] >= lift_code(inst.config)           # ends lifted


def test_scan_line_heights_run_from_a_to_b_and_end_lifted(backend):
    inst = backend.inst
    a, b = (FEATURE[0] - 1000.0, FEATURE[1]), (FEATURE[0] + 1000.0, FEATURE[1])
    h = inst.scan_line(a, b, 41)
    assert h.shape == (41,) and np.all(np.isfinite(h))
    assert abs(int(np.argmax(h)) - 20) <= 1                      # the feature is mid-line
    assert h.max() - min(h[0], h[-1]) > 30.0
    end = inst.config.codes_to_nm(inst.position())
    assert end[:2] == pytest.approx(b, abs=2.0) and inst.position()[2] >= lift_code(inst.config)


# -- time --------------------------------------------------------------------------------------------------

def test_the_clock_is_monotonic_and_a_chunk_plays_within_its_write(backend):
    inst = backend.inst
    times = [inst.clock()]
    for step in range(2):
        path = pressed_path(inst)
        before = inst.clock()
        block = inst.write(path)
        after = inst.clock()
        assert len(block) == len(path) and block.s_n.shape == block.s_l.shape == (len(path),)
        assert np.all(np.diff(block.t) >= 0)
        assert before <= block.t[0] and block.t[-1] <= after + 1e-9
        np.testing.assert_array_equal(inst.position(), path[-1])     # the last sample written
        times += [before, *block.t[[0, -1]], after]
        inst.scan_line((500.0, 500.0), (900.0, 500.0), 8)
        times.append(inst.clock())
        inst.full_scan(16, (500.0, 500.0, 1500.0, 1500.0))
        times.append(inst.clock())
        inst.signals()
        inst.park()
        times.append(inst.clock())
    assert np.all(np.diff(times) >= 0), times
    assert times[-1] > times[0]
