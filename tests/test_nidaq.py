"""The NI-DAQmx backend at the nidaqmx boundary: no hardware here, so a fake module
(tests/nidaqmx_fake.py) records every call and simulates the device behind it."""

from __future__ import annotations

import sys
import tomllib

import numpy as np
import pytest
from nidaqmx_fake import (UNDERFLOW, AcquisitionType, FakeNidaqmx, OverwriteMode, RegenerationMode,
                          TerminalConfiguration)

from nanoasm.errors import InstrumentLimitError, NanoasmError
from nanoasm.examples import path as example_path
from nanoasm.executor.feedback_scan import z_code
from nanoasm.executor.instrument_file import instrument_from_dict
from nanoasm.executor.nidaq import DaqDriverNotFound, NiDaqError, NiDaqInstrument
from nanoasm.instrument import Instrument, check_samples, ramp

EXAMPLE = example_path("instrument_ni.toml")


def instrument_file(**daq):
    doc = tomllib.loads(EXAMPLE.read_text())
    doc["daq"].update(daq)
    return instrument_from_dict(doc, "lab.toml")


def identity_signal(volts, index):
    """S_n = x volts, S_l = y volts, height = z volts, of the same clock edge."""
    return volts.copy()


def open_inst(signal=identity_signal, **daq):
    fake = FakeNidaqmx(signal)
    return NiDaqInstrument(instrument_file(**daq), nidaqmx_module=fake), fake


def played_codes(inst, fake):
    return inst.config.volts_to_codes(fake.played_volts())


def move(inst, dx=0.0, dy=0.0, z=None):
    """A chunk from the present position moving by (dx, dy) nm and to height z nm."""
    cfg = inst.config
    here = inst.position()
    nm = cfg.codes_to_nm(here)
    nm[:2] += (dx, dy)
    if z is not None:
        nm[2] = z
    return ramp(here, cfg.nm_to_codes(nm), cfg)


def assert_safe_history(inst, fake):
    """Everything the DAC ever played, from the rest it started at, passes the limit check."""
    check_samples(played_codes(inst, fake), inst.config, previous=inst.config.rest_codes())


def assert_parked_and_closed(inst, fake):
    assert all(t.closed for t in fake.tasks) and fake.tasks
    assert all(t.log[-2:] == ["stop", "close"] for t in fake.tasks)
    np.testing.assert_array_equal(played_codes(inst, fake)[-1], inst.config.rest_codes())
    np.testing.assert_array_equal(inst.position(), inst.config.rest_codes())
    assert_safe_history(inst, fake)


# -- tasks, channels, timing ---------------------------------------------------------------------------

def test_is_an_instrument():
    inst, _ = open_inst()
    with inst:
        assert isinstance(inst, Instrument)
        assert inst.config.sample_rate == 10000.0


def test_channels_timing_and_regeneration_off():
    inst, fake = open_inst()
    with inst:
        ao, ai = fake.tasks
        assert [c["physical"] for c in ao.channels] == ["Dev1/ao0", "Dev1/ao1", "Dev1/ao2"]
        assert all((c["min_val"], c["max_val"]) == (-10.0, 10.0) for c in ao.channels)
        assert ao.timing_args == {"rate": 10000.0, "source": "", "sample_mode": AcquisitionType.CONTINUOUS,
                                      "samps_per_chan": 10000}
        assert ao.out_stream.regen_mode is RegenerationMode.DONT_ALLOW_REGENERATION
        assert ao.event[0] == 500
        assert [w.auto_start for w in fake.writers] == [False]

        assert [c["physical"] for c in ai.channels] == ["Dev1/ai0", "Dev1/ai1", "Dev1/ai2"]
        assert all(c["terminal"] is TerminalConfiguration.DIFF for c in ai.channels)
        assert ai.timing_args == {"rate": 10000.0, "source": "/Dev1/ao/SampleClock",
                                      "sample_mode": AcquisitionType.CONTINUOUS, "samps_per_chan": 10000}
        assert ai.in_stream.overwrite is OverwriteMode.OVERWRITE_UNREAD_SAMPLES
        assert fake.starts == [ai, ao]  # AI armed on the AO clock before the AO starts
        # the prefill: lead_chunks x chunk_size samples of the rest output, before the start
        first = fake.writes[0]
        assert first.shape == (3, 2000)
        np.testing.assert_array_equal(first.T, np.tile(inst.config.codes_to_volts(inst.config.rest_codes()),
                                                       (2000, 1)))


def test_terminal_and_ranges_come_from_the_file():
    doc = tomllib.loads(EXAMPLE.read_text())
    doc["daq"]["ai"].update(terminal="rse", signal_range=[-5.0, 5.0], height_range=[-2.0, 2.0])
    fake = FakeNidaqmx()
    with NiDaqInstrument(instrument_from_dict(doc, "lab.toml"), nidaqmx_module=fake):
        ai = fake.tasks[1]
        assert all(c["terminal"] is TerminalConfiguration.RSE for c in ai.channels)
        assert [(c["min_val"], c["max_val"]) for c in ai.channels] == [(-5, 5), (-5, 5), (-2, 2)]


# -- writing -------------------------------------------------------------------------------------------

def test_written_volts_are_the_codes_and_the_signals_are_their_own():
    inst, fake = open_inst()
    with inst:
        chunk = move(inst, 900.0, -400.0, z=100.0)
        block = inst.write(chunk)
        rate = inst.config.sample_rate
        start = round(block.t[0] * rate) - 1
        volts = inst.config.codes_to_volts(chunk)
        played = fake.played_volts()
        np.testing.assert_array_equal(played[start:start + len(chunk)], volts)
        # AI on the AO clock: S_n, S_l of each sample are that sample's x, y volts
        np.testing.assert_array_equal(block.s_n, volts[:, 0])
        np.testing.assert_array_equal(block.s_l, volts[:, 1])
        np.testing.assert_allclose(np.diff(block.t), 1 / rate)
        assert inst.clock() >= block.t[-1]
        np.testing.assert_array_equal(inst.position(), chunk[-1])
        for w in fake.writes:
            assert w.dtype == np.float64 and w.flags.c_contiguous and w.shape[0] == 3
        assert {w.shape[1] for w in fake.writes[1:]} == {500}


def test_the_dac_holds_between_writes():
    inst, fake = open_inst()
    with inst:
        a = inst.write(move(inst, 300.0))
        b = inst.write(move(inst, 300.0))
        rate = inst.config.sample_rate
        i, j = round(a.t[-1] * rate), round(b.t[0] * rate) - 1
        gap = played_codes(inst, fake)[i:j]
        assert len(gap) > 0
        assert (gap == played_codes(inst, fake)[i - 1]).all()
        assert b.t[0] > a.t[-1]


def test_signals_are_the_latest_ai_sample():
    inst, _ = open_inst()
    with inst:
        inst.write(move(inst, 500.0, 200.0))
        s_n, s_l = inst.signals()
        x, y, _ = inst.config.codes_to_volts(inst.position())
        assert (s_n, s_l) == (x, y)


def test_clock_is_the_daq_count_of_played_samples():
    inst, fake = open_inst()
    with inst:
        assert inst.clock() == 0.0
        inst.write(move(inst, 100.0))
        ao = fake.tasks[0]
        assert inst.clock() == ao.generated / 10000.0
        before = inst.clock()
        inst.park()
        after_park = inst.clock()
        assert after_park > before
        inst.write(move(inst, 100.0))  # a new stream continues the clock
        assert inst.clock() > after_park
        assert len(fake.tasks) == 4


@pytest.mark.parametrize("bad, message", [
    ("nan", "NaN"),
    ("negative", "outside the DAC range"),
    ("too_high", "outside the DAC range"),
    ("jump_from_here", "exceeds"),
    ("jump_inside", "exceeds"),
    ("fraction", "not an integer"),
    ("shape", "(n, 3)"),
])
def test_chunks_beyond_the_limits_are_refused_before_any_write(bad, message):
    inst, fake = open_inst()
    with inst:
        inst.write(move(inst, 200.0))
        here = inst.position()
        chunk = move(inst, 200.0).astype(float)
        if bad == "nan":
            chunk[3, 1] = np.nan
        elif bad == "negative":
            chunk[2, 0] = -1
        elif bad == "too_high":
            chunk[2, 2] = 2 ** 16
        elif bad == "jump_from_here":
            chunk = chunk + np.array([40, 0, 0])
        elif bad == "jump_inside":
            chunk[5:, 1] += 40
        elif bad == "fraction":
            chunk[1, 0] += 0.5
        else:
            chunk = chunk[:, :2]
        calls, played = len(fake.writes), len(fake.played_volts())
        with pytest.raises(InstrumentLimitError, match=message.replace("(", r"\(").replace(")", r"\)")):
            inst.write(chunk)
        assert len(fake.writes) == calls and len(fake.played_volts()) == played
        np.testing.assert_array_equal(inst.position(), here)
        inst.write(move(inst, -100.0))  # the stream goes on from where it was
    assert_parked_and_closed(inst, fake)


# -- park and clean-up ------------------------------------------------------------------------------------

def test_park_lifts_then_ramps_within_the_slew_limit_and_closes():
    inst, fake = open_inst()
    cfg = inst.config
    inst.write(move(inst, z=0.0))  # down to the surface...
    inst.write(move(inst, 4000.0, -3000.0))  # ...and across it
    inst.write(move(inst, z=-cfg.preload))  # pressing
    n = len(fake.played_volts())
    inst.park()
    path = played_codes(inst, fake)[n:]
    top = cfg.rest_codes()[2]
    rising = np.flatnonzero(path[:, 2] < top)
    moving = np.flatnonzero(np.any(path[:, :2] != path[0, :2], axis=1))
    assert rising.size and moving.size and rising.max() < moving.min()  # Z first, then XY
    assert (path[moving, 2] == top).all()
    assert_parked_and_closed(inst, fake)
    tasks, writes = len(fake.tasks), len(fake.writes)
    inst.park()  # idempotent: parked and closed, it does nothing
    inst.close()
    assert (len(fake.tasks), len(fake.writes)) == (tasks, writes)


class Boom(Exception):
    pass


@pytest.mark.parametrize("exit_by", ["normal", Boom, KeyboardInterrupt])
def test_the_context_manager_parks_on_every_exit(exit_by):
    inst, fake = open_inst()

    def body():
        with inst:
            inst.write(move(inst, 2500.0, 1500.0, z=0.0))
            inst.write(move(inst, z=-50.0))
            if exit_by != "normal":
                raise exit_by()

    if exit_by == "normal":
        body()
    else:
        with pytest.raises(exit_by):
            body()
    assert_parked_and_closed(inst, fake)


def test_ctrl_c_in_the_middle_of_a_write_parks_from_the_last_sample_sent():
    inst, fake = open_inst()
    cfg = inst.config
    inst.write(move(inst, z=0.0))
    long = move(inst, 40000.0)  # 20000 samples, 40 reads
    fake.interrupt_read = fake.reads + 3
    with pytest.raises(KeyboardInterrupt), inst:
        inst.write(long)
    assert_parked_and_closed(inst, fake)
    x_reached = played_codes(inst, fake)[:, 0].max()
    assert cfg.rest_codes()[0] < x_reached < long[-1, 0]  # the rest of the chunk was never played


def test_an_interrupted_write_stops_at_the_last_sample_sent():
    inst, fake = open_inst()
    inst.write(move(inst, z=0.0))
    long = move(inst, 40000.0)
    fake.interrupt_read = fake.reads + 3
    with pytest.raises(KeyboardInterrupt):
        inst.write(long)
    here = inst.position()
    assert here[0] < long[-1, 0]
    inst.write(move(inst, -1000.0))  # the caller goes on from position()
    assert played_codes(inst, fake)[:, 0].max() == here[0]  # the rest of the chunk never played
    inst.park()
    assert_parked_and_closed(inst, fake)


def test_ctrl_c_during_park_leaves_the_true_dac_output_and_parks_again():
    inst, fake = open_inst()
    inst.write(move(inst, 30000.0, z=0.0))
    fake.interrupt_read = fake.reads + 2  # inside the park ramp, with samples still buffered
    with pytest.raises(KeyboardInterrupt):
        inst.park()
    assert all(t.closed for t in fake.tasks)
    written = inst.config.volts_to_codes(np.hstack(fake.writes).T)
    last_played = played_codes(inst, fake)[-1]
    assert not np.array_equal(written[-1], last_played)  # the buffer still held samples...
    np.testing.assert_array_equal(inst.position(), last_played)  # ...the DAC holds the last played
    inst.park()
    assert_parked_and_closed(inst, fake)


def test_a_driver_error_while_streaming_is_one_line_and_the_tasks_close():
    inst, fake = open_inst()
    inst.write(move(inst, z=0.0))
    fake.fail_write_call = len(fake.writes) + 2
    with pytest.raises(NiDaqError) as err:
        inst.write(move(inst, 30000.0))
    line = str(err.value)
    assert "\n" not in line and "device was removed" in line and "-201003" in line
    ao = fake.tasks[0]
    for _ in range(20):  # time passes: the DAC plays what was buffered, nobody refills
        if not ao.play_block():
            break
    assert ao.error.error_code == UNDERFLOW and fake.write_calls == fake.fail_write_call
    with pytest.raises(NiDaqError):  # park cannot play on a stopped stream...
        inst.park()
    assert all(t.closed for t in fake.tasks)  # ...but closes the tasks
    last = played_codes(inst, fake)[-1]
    np.testing.assert_array_equal(inst.position(), last)  # where the DAC really stopped
    fake.fail_write_call = None
    inst.park()  # a new stream from there, lifted and ramped to rest
    assert len(fake.tasks) == 4
    assert_parked_and_closed(inst, fake)


def test_a_driver_error_at_open_closes_what_was_opened():
    fake = FakeNidaqmx()
    fake.fail_channel = "Dev1/ai1"
    with pytest.raises(NiDaqError) as err:
        NiDaqInstrument(instrument_file(), nidaqmx_module=fake)
    line = str(err.value)
    assert line.startswith("NI-DAQmx failed opening the DAQ tasks: Physical channel specified does not "
                           "exist") and "-200170" in line and "\n" not in line
    assert fake.tasks and all(t.closed for t in fake.tasks)
    assert fake.writes == []


def test_missing_driver_in_a_fake_module_is_the_one_line_error():
    fake = FakeNidaqmx()
    fake.task_error = fake.errors.DaqNotFoundError
    with pytest.raises(DaqDriverNotFound) as err:
        NiDaqInstrument(instrument_file(), nidaqmx_module=fake)
    assert str(err.value) == "NI-DAQmx driver not found: install NI-DAQmx or use nanoasm dry-run"
    assert isinstance(err.value, NanoasmError)


def test_missing_nidaqmx_package_is_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "nidaqmx", None)  # import nidaqmx -> ImportError
    with pytest.raises(NiDaqError, match=r"^the nidaqmx package is not installed: pip install nidaqmx"):
        NiDaqInstrument(instrument_file())


# -- scans under the controller's feedback ------------------------------------------------------------------

def step_height(volts, index):
    """Height signal 0.4 V where x > 45 µm (x volts > 0), else 0; S_n, S_l zero."""
    out = np.zeros_like(volts)
    out[2] = np.where(volts[0] > 0.0, 0.4, 0.0)
    return out


def test_scan_line_reads_the_height_channel_engaged_and_ends_lifted():
    inst, fake = open_inst(step_height)
    cfg = inst.config
    with inst:
        n0 = len(fake.played_volts())
        heights = inst.scan_line((44000.0, 45000.0), (46000.0, 45000.0), 21)
        assert heights.shape == (21,)
        k = inst.file.imaging.height_nm_per_volt
        np.testing.assert_allclose(heights[:10], 0.0)
        np.testing.assert_allclose(heights[11:], 0.4 * k)
        path = played_codes(inst, fake)[n0:]
        surface, lift = z_code(cfg, 0.0), z_code(cfg, cfg.lift)
        on_line = path[:, 1] == cfg.nm_to_codes(np.array([0, 45000.0, 0]))[1]
        xy_moves = np.flatnonzero(np.any(np.diff(path[:, :2], axis=0) != 0, axis=1)) + 1
        # XY moves lifted, or at the surface along the line
        assert np.all((path[xy_moves, 2] >= lift) | (on_line[xy_moves] & (path[xy_moves, 2] == surface)))
        assert inst.position()[2] >= lift
        assert_safe_history(inst, fake)


def x_ramp(volts, index):
    """Height signal with 0.25 nm of height per nm of x about x = 45 µm."""
    out = np.zeros_like(volts)
    out[2] = ((volts[0] + 10.0) * 4500.0 - 45000.0) / 1000.0
    return out


def test_scan_line_points_are_evenly_spaced_from_a_to_b():
    inst, _ = open_inst(x_ramp)
    with inst:
        heights = inst.scan_line((44000.0, 45000.0), (46000.0, 45000.0), 21)
        x = np.linspace(44000.0, 46000.0, 21)
        # interior points average a symmetric window; the two end points half a window
        np.testing.assert_allclose(heights[1:-1], 0.25 * (x[1:-1] - 45000.0), atol=0.2)


def plane(volts, index):
    """Height signal proportional to 1e-4 x + 2e-4 y (nm), from the x, y volts."""
    x = (volts[0] + 10.0) * 4500.0
    y = (volts[1] + 10.0) * 4500.0
    out = np.zeros_like(volts)
    out[2] = (1e-4 * x + 2e-4 * y) / 250.0
    return out


def test_full_scan_images_the_height_signal_at_pixel_centres():
    inst, fake = open_inst(plane)
    cfg = inst.config
    with inst:
        img = inst.full_scan(4, (1000.0, 2000.0, 3000.0, 4000.0))
        assert img.shape == (4, 4) and img.pixel_size == 500.0 and img.origin == (1000.0, 2000.0)
        x, y = img.pixel_centres()
        np.testing.assert_allclose(img.height, 1e-4 * x[None, :] + 2e-4 * y[:, None], atol=0.01)
        assert inst.position()[2] >= z_code(cfg, cfg.lift)
        assert_safe_history(inst, fake)


@pytest.mark.parametrize("call", [
    lambda inst: inst.scan_line((-10.0, 100.0), (500.0, 100.0), 8),
    lambda inst: inst.scan_line((100.0, 100.0), (100.0, 90001.0), 8),
    lambda inst: inst.full_scan(8, (80000.0, 0.0, 95000.0, 1000.0)),
])
def test_scans_outside_the_range_send_nothing(call):
    inst, fake = open_inst()
    with inst:
        calls = len(fake.writes)
        with pytest.raises(InstrumentLimitError, match="nothing sent"):
            call(inst)
        assert len(fake.writes) == calls


@pytest.mark.parametrize("call, message", [
    (lambda inst: inst.scan_line((0, 0), (10, 10), 1), "n must be an integer of at least 2"),
    (lambda inst: inst.scan_line((0, 0), (10, np.nan), 5), "b must be two finite numbers"),
    (lambda inst: inst.full_scan(True), "pixels must be an integer"),
    (lambda inst: inst.full_scan(8, (10, 10, 5, 20)), "x1 > x0"),
])
def test_bad_scan_arguments_are_value_errors(call, message):
    inst, _ = open_inst()
    with inst, pytest.raises(ValueError, match=message):
        call(inst)


# -- the real nidaqmx package ----------------------------------------------------------------------------

def test_the_real_nidaqmx_without_its_driver_gives_the_one_line_error():
    nidaqmx = pytest.importorskip("nidaqmx")
    from nanoasm.executor.nidaq_stream import NiApi

    api = NiApi.load()
    assert api.Writer.__name__ == "AnalogMultiChannelWriter"
    assert api.Reader.__name__ == "AnalogMultiChannelReader"
    assert api.constants.RegenerationMode.DONT_ALLOW_REGENERATION.value == 10158
    try:
        nidaqmx.Task().close()
    except nidaqmx.errors.DaqNotFoundError:
        pass
    else:
        pytest.skip("the NI-DAQmx driver is installed here")
    with pytest.raises(DaqDriverNotFound) as err:
        NiDaqInstrument(instrument_file())
    assert str(err.value) == "NI-DAQmx driver not found: install NI-DAQmx or use nanoasm dry-run"
