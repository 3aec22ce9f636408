"""The Instrument protocol's value types and the DAC limit check."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from nanoasm.errors import InstrumentLimitError
from nanoasm.instrument import (
    HeightImage,
    Instrument,
    InstrumentConfig,
    SignalBlock,
    check_samples,
    ramp,
)
from nanoasm.param import ParamError

CFG = InstrumentConfig()


def codes_at(*nm) -> np.ndarray:
    return CFG.nm_to_codes(np.array(nm, float))


# -- configuration and conversions -------------------------------------------------------------

def test_defaults_follow_the_seed_scanner():
    assert CFG.xy_range == (90000.0, 90000.0) and CFG.z_range == 5000.0
    assert CFG.max_code == 65535
    np.testing.assert_allclose(CFG.nm_per_code, [90000 / 65535, 90000 / 65535, 5000 / 65535])
    assert CFG.max_step == pytest.approx(50.0)


def test_axis_ends_map_to_code_ends():
    np.testing.assert_array_equal(CFG.nm_to_codes(CFG.lower), [0, 0, 0])
    np.testing.assert_array_equal(CFG.nm_to_codes(CFG.upper), [65535] * 3)
    np.testing.assert_allclose(CFG.codes_to_nm(np.array([0, 0, 0])), CFG.lower)


@given(st.lists(st.floats(0, 1), min_size=3, max_size=3))
def test_nm_code_round_trip_within_half_a_code(frac):
    nm = CFG.lower + np.array(frac) * (CFG.upper - CFG.lower)
    back = CFG.codes_to_nm(CFG.nm_to_codes(nm))
    assert np.all(np.abs(back - nm) <= CFG.nm_per_code / 2 + 1e-9)
    np.testing.assert_allclose(CFG.volts_to_nm(CFG.nm_to_volts(nm)), nm, atol=1e-9)


def test_volts_to_codes_refuses_nan():
    with pytest.raises(InstrumentLimitError, match="non-finite"):
        CFG.volts_to_codes(np.array([0.0, np.nan, 0.0]))


def test_rest_sample_is_lifted_and_centred():
    rest = CFG.rest_codes()
    nm = CFG.codes_to_nm(rest)
    assert nm[2] == pytest.approx(CFG.upper[2])
    np.testing.assert_allclose(nm[:2], [45000, 45000], atol=CFG.nm_per_code[0])


@pytest.mark.parametrize("kwargs, key", [
    ({"volt_range": (10.0, -10.0)}, "volt_range"),
    ({"lift": 2500.0}, "lift"),
    ({"preload": 3000.0}, "preload"),
    ({"sample_rate": 0.0}, "sample_rate"),
    ({"nm_per_volt": (1.0, 1.0)}, "nm_per_volt"),
    ({"dac_bits": 4}, "dac_bits"),
])
def test_config_rejects_bad_values(kwargs, key):
    with pytest.raises(ParamError) as e:
        InstrumentConfig(**kwargs)
    assert e.value.key == key


# -- check_samples: accept ------------------------------------------------------------------------

@st.composite
def valid_chunks(draw):
    """A random walk of codes inside the DAC range whose every step is within the slew limit."""
    n = draw(st.integers(1, 60))
    q = CFG.nm_per_code
    lim_xy = int(CFG.max_step / math.sqrt(2) / q[0])
    lim_z = int(CFG.max_step / q[2])
    start = np.array([draw(st.integers(0, CFG.max_code)) for _ in range(3)])
    steps = np.array([[draw(st.integers(-lim_xy, lim_xy)), draw(st.integers(-lim_xy, lim_xy)),
                       draw(st.integers(-lim_z, lim_z))] for _ in range(n)])
    codes = [start]
    for s in steps:
        codes.append(np.clip(codes[-1] + s, 0, CFG.max_code))
    arr = np.array(codes)
    return arr[0], arr[1:]


@given(valid_chunks())
def test_valid_chunks_pass(chunk):
    previous, codes = chunk
    out = check_samples(codes, CFG, previous=previous)
    assert out.dtype == np.int64
    np.testing.assert_array_equal(out, codes)
    check_samples(codes.astype(float), CFG)  # integral floats are codes too


@given(st.lists(st.floats(0, 1), min_size=6, max_size=6), st.floats(2000.0, 1e6))
def test_ramps_pass_and_end_at_the_target(frac, speed):
    f = np.array(frac)
    a = CFG.nm_to_codes(CFG.lower + f[:3] * (CFG.upper - CFG.lower))
    b = CFG.nm_to_codes(CFG.lower + f[3:] * (CFG.upper - CFG.lower))
    path = ramp(a, b, CFG, speed=speed)
    if np.array_equal(a, b):
        assert path.shape == (0, 3)
        return
    np.testing.assert_array_equal(path[-1], b)
    check_samples(path, CFG, previous=a)


# -- check_samples: reject ------------------------------------------------------------------------

@given(valid_chunks(), st.data())
def test_nan_anywhere_is_rejected(chunk, data):
    _, codes = chunk
    bad = codes.astype(float)
    i = data.draw(st.integers(0, len(bad) - 1))
    a = data.draw(st.integers(0, 2))
    bad[i, a] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    with pytest.raises(InstrumentLimitError, match=f"sample {i}: {'xyz'[a]} is"):
        check_samples(bad, CFG)


@given(valid_chunks(), st.data())
def test_codes_outside_the_dac_are_rejected(chunk, data):
    _, codes = chunk
    bad = codes.copy()
    i = data.draw(st.integers(0, len(bad) - 1))
    a = data.draw(st.integers(0, 2))
    bad[i, a] = data.draw(st.one_of(st.integers(-10**6, -1), st.integers(CFG.max_code + 1, 10**6)))
    with pytest.raises(InstrumentLimitError, match="outside the DAC range"):
        check_samples(bad, CFG)


def test_codes_beyond_the_scanner_range_are_rejected():
    # an amplifier gain that over-drives X: the DAC's top codes reach past the 90 µm travel
    cfg = InstrumentConfig(nm_per_volt=(5000.0, 4500.0, 250.0))
    inside = cfg.nm_to_codes(np.array([89990.0, 100.0, 0.0]))
    check_samples(inside[None, :], cfg)
    beyond = np.array([[cfg.max_code, 100, 30000]])
    with pytest.raises(InstrumentLimitError, match=r"sample 0: x = 100000.0 nm outside the scanner range"):
        check_samples(beyond, cfg)


@given(valid_chunks(), st.data())
def test_a_step_beyond_the_speed_limit_is_rejected(chunk, data):
    _, codes = chunk
    codes = np.vstack([codes, codes[-1:]])  # at least two samples
    i = data.draw(st.integers(1, len(codes) - 1))
    axis = data.draw(st.integers(0, 2))
    jump = int(2 * CFG.max_step / CFG.nm_per_code[axis]) + 3
    bad = codes.copy()
    bad[i:, axis] = np.where(bad[i - 1, axis] > CFG.max_code // 2, bad[i - 1, axis] - jump,
                             bad[i - 1, axis] + jump)
    with pytest.raises(InstrumentLimitError, match=f"sample {i - 1} -> sample {i}: .* exceeds"):
        check_samples(bad, CFG)


def test_the_step_from_the_previous_chunk_counts():
    a = codes_at(1000, 1000, 0)
    b = codes_at(1100, 1000, 0)  # 100 nm in one sample at a 50 nm/sample limit
    check_samples(b[None, :], CFG)
    with pytest.raises(InstrumentLimitError, match="previous sample -> sample 0: XY step"):
        check_samples(b[None, :], CFG, previous=a)
    with pytest.raises(InstrumentLimitError, match="previous sample: z is nan"):
        check_samples(b[None, :], CFG, previous=np.array([1.0, 2.0, np.nan]))


def test_diagonal_steps_use_the_euclidean_limit():
    a = codes_at(1000, 1000, 0)
    ok = codes_at(1000 + 35, 1000 + 35, 0)  # 49.5 nm
    too_far = codes_at(1000 + 40, 1000 + 40, 0)  # 56.6 nm
    check_samples(np.array([a, ok]), CFG)
    with pytest.raises(InstrumentLimitError, match="XY step"):
        check_samples(np.array([a, too_far]), CFG)


@pytest.mark.parametrize("bad, message", [
    (np.zeros((0, 3), int), "shape"),
    (np.zeros((4, 2), int), "shape"),
    (np.zeros(3, int), "shape"),
    (np.array([[1.5, 2.0, 3.0]]), "not an integer"),
    (np.array([["1", "2", "3"]]), "must be integers"),
    (np.array([[1e300, 0.0, 0.0]]), "outside the DAC range"),
])
def test_malformed_chunks_are_rejected(bad, message):
    with pytest.raises(InstrumentLimitError, match=message):
        check_samples(bad, CFG)


# -- signals and the protocol -----------------------------------------------------------------------

def test_signal_block_needs_matching_1d_arrays():
    blk = SignalBlock(np.arange(3) / 1000, np.zeros(3), np.ones(3))
    assert len(blk) == 3 and blk.s_l.dtype == float
    with pytest.raises(ValueError, match="one length"):
        SignalBlock(np.arange(3), np.zeros(2), np.zeros(3))
    with pytest.raises(ValueError, match="1-D"):
        SignalBlock(np.zeros((3, 1)), np.zeros(3), np.zeros(3))


class _Bench:
    """The smallest instrument: a stage with no sample (checks the protocol's shape)."""

    def __init__(self) -> None:
        self._config = InstrumentConfig()
        self._t = 0.0
        self._last = self._config.rest_codes()

    @property
    def config(self) -> InstrumentConfig:
        return self._config

    def clock(self) -> float:
        return self._t

    def write(self, chunk):
        c = check_samples(chunk, self._config, previous=self._last)
        t = self._t + np.arange(1, len(c) + 1) / self._config.sample_rate
        self._t, self._last = float(t[-1]), c[-1]
        return SignalBlock(t, np.zeros(len(c)), np.zeros(len(c)))

    def full_scan(self, pixels, region=None):
        return HeightImage(np.zeros((pixels, pixels)), 10.0, source="simulated")

    def scan_line(self, a, b, n):
        return np.zeros(n)

    def signals(self):
        return 0.0, 0.0

    def position(self):
        return self._last.copy()

    def park(self) -> None:
        path = ramp(self._last, self._config.rest_codes(), self._config)
        if len(path):
            self.write(path)


def test_protocol_is_runtime_checkable():
    bench = _Bench()
    assert isinstance(bench, Instrument)

    members = {k: v for k, v in vars(_Bench).items() if k != "park"}
    NoPark = type("NoPark", (), members)
    assert not isinstance(NoPark(), Instrument)
    assert not isinstance(object(), Instrument)


def test_a_bench_streams_and_parks_within_limits():
    bench = _Bench()
    target = codes_at(1000, 2000, 300)
    path = ramp(bench.config.rest_codes(), target, bench.config)
    blk = bench.write(path)
    assert len(blk) == len(path) and bench.clock() == pytest.approx(len(path) / 1000)
    with pytest.raises(InstrumentLimitError):
        bench.write(codes_at(5000, 2000, 300)[None, :])
    bench.park()
    bench.park()
    np.testing.assert_array_equal(bench._last, bench.config.rest_codes())
