"""The instrument file (nanoasm.instrument/1): the example loads, every bad key is one line."""

from __future__ import annotations

import json
import math
import tomllib

import pytest

from nanoasm.errors import InputError
from nanoasm.examples import path as example_path
from nanoasm.executor.instrument_file import SCANNER_REQUIRED, DaqConfig, InstrumentFile, load_instrument_config
from nanoasm.fileio import dumps_toml
from nanoasm.param import ParamError

from doc_edits import DELETE

EXAMPLE = example_path("instrument_ni.toml")


def example_doc() -> dict:
    return tomllib.loads(EXAMPLE.read_text())


def test_the_example_loads():
    f = load_instrument_config(EXAMPLE)
    assert isinstance(f, InstrumentFile) and f.name == "Bioscope + PCIe-6363"
    s, d, im = f.scanner, f.daq, f.imaging
    assert s.xy_range == (90000.0, 90000.0) and s.nm_per_volt == (4500.0, 4500.0, 250.0)
    assert s.sample_rate == 10000.0 and s.max_speed == 20000.0 and s.max_step == 2.0
    assert (d.device, d.ao, d.ai) == ("Dev1", ("ao0", "ao1", "ao2"), ("ai0", "ai1", "ai2"))
    assert d.physical("ao2") == "Dev1/ao2" and d.clock_terminal == "/Dev1/ao/SampleClock"
    assert (d.terminal, d.chunk_size, d.lead_chunks, d.buffer_size) == ("differential", 500, 4, 10000)
    assert (im.line_speed, im.full_scan_speed, im.settle, im.height_nm_per_volt) == (2000, 20000, 0.2, 250)
    assert f.latency == pytest.approx(0.25)


def test_json_and_defaults(tmp_path):
    doc = example_doc()
    del doc["daq"]["chunk_size"], doc["daq"]["lead_chunks"], doc["daq"]["buffer_size"], doc["daq"]["timeout"]
    del doc["daq"]["ai"]["terminal"], doc["imaging"]["settle"], doc["scanner"]["lift"]
    p = tmp_path / "lab.json"
    p.write_text(json.dumps(doc))
    f = load_instrument_config(p)
    assert (f.daq.chunk_size, f.daq.lead_chunks, f.daq.buffer_size, f.daq.timeout) == (1000, 4, 20000, 10.0)
    assert f.daq.terminal == "differential" and f.imaging.settle == 0.2 and f.scanner.lift == 300.0


def _set(doc, path, value):
    *head, last = path.split(".")
    t = doc
    for k in head:
        t = t[k]
    if value is DELETE:
        del t[last]
    else:
        t[last] = value


BAD = [
    # unknown keys, with the nearest allowed one
    ("scaling", {"x": 1.0}, "scaling: unknown key (allowed: backend, baseline, calibration, cantilever, daq, format, friction, imaging, name, nanonis, scanner)"),
    ("daq.ai.hieght", "ai3", "daq.ai.hieght: unknown key (did you mean 'height'?)"),
    ("scanner.nm_per_volts", [1, 2, 3], "scanner.nm_per_volts: unknown key (did you mean 'nm_per_volt'?)"),
    ("imaging.line_sped", 10.0, "imaging.line_sped: unknown key (did you mean 'line_speed'?)"),
    ("daq.sample_rate", 10000, "daq.sample_rate: unknown key"),
    # missing
    ("scanner.nm_per_volt", DELETE, "scanner.nm_per_volt: missing required key"),
    ("imaging", DELETE, "imaging: missing required key"),
    ("imaging.height_nm_per_volt", DELETE, "imaging.height_nm_per_volt: missing required key"),
    ("daq.ao.z", DELETE, "daq.ao.z: missing required key"),
    ("daq.device", DELETE, "daq.device: missing required key"),
    ("format", DELETE, "format: missing required key (expected 'nanoasm.instrument/1')"),
    # wrong type
    ("daq.chunk_size", "500", "daq.chunk_size: must be an integer, got a string '500'"),
    ("daq.chunk_size", 500.5, "daq.chunk_size: must be an integer, got 500.5"),
    ("daq.device", 1, "daq.device: must be a string, got an integer 1"),
    ("daq.ai", "ai0", "daq.ai: must be a table, got a string"),
    ("daq.ai.signal_range", 10.0, "daq.ai.signal_range: must be an array of two numbers [low, high]"),
    ("scanner.xy_range", [1.0, "a"], "scanner.xy_range: y must be a number, got a string 'a'"),
    ("imaging.settle", True, "imaging.settle: must be a number, got a boolean True"),
    # non-finite
    ("scanner.max_speed", math.inf, "scanner.max_speed: must be finite, got inf"),
    ("imaging.line_speed", math.nan, "imaging.line_speed: must be finite, got nan"),
    ("daq.ai.height_range", [-10.0, math.inf], "daq.ai.height_range: high must be finite, got inf"),
    # out of range, alone or against another key
    ("daq.lead_chunks", 1, "daq.lead_chunks: must be at least 2, got 1"),
    ("daq.timeout", 0, "daq.timeout: must be positive, got 0"),
    ("scanner.sample_rate", -0.5, "scanner.sample_rate: must be positive, got -0.5"),
    ("imaging.height_nm_per_volt", 0, "imaging.height_nm_per_volt: must not be zero"),
    ("imaging.line_speed", 25000, "imaging.line_speed: must be at most scanner.max_speed (20000 nm/s), got 25000"),
    ("daq.chunk_size", 20, ("daq.chunk_size: 20 samples is 2 ms at 10000 Hz; refills must be at least 5 ms "
                            "apart (chunk_size >= 50)")),
    ("daq.buffer_size", 2000, "daq.buffer_size: must hold (lead_chunks + 1) x chunk_size = 2500 samples, got 2000"),
    ("daq.ai.signal_range", [5.0, -5.0], "daq.ai.signal_range: low end must be below the high end, got [5, -5]"),
    ("daq.ai.terminal", "diff", ("daq.ai.terminal: must be one of 'differential', 'rse', 'nrse', "
                                 "'pseudodifferential', got 'diff'")),
    ("daq.ao.x", "Dev1/ao0", ("daq.ao.x: must be a channel of the device such as 'ao0' (without the device "
                              "name), got 'Dev1/ao0'")),
    ("daq.ai.height", "ao2", "daq.ai.height: must be a channel of the device such as 'ai0'"),
    ("daq.ao.y", "ao0", "daq.ao.y: channel 'ao0' is already ao.x"),
    ("daq.device", "Dev 1", "daq.device: must be an NI device name such as 'Dev1', got 'Dev 1'"),
    ("scanner.lift", 4000, "scanner.lift: must be below the top of the Z range (2500 nm)"),
    # format
    ("format", "nanoasm.instrument/2", "format: unsupported version 'nanoasm.instrument/2'"),
    ("format", "nanoasm.scene/1", "format: this is a 'nanoasm.scene/1' file, expected 'nanoasm.instrument/1'"),
    ("format", "ni-daq", "format: unknown format 'ni-daq' (expected 'nanoasm.instrument/1')"),
]


@pytest.mark.parametrize("key, value, message", BAD, ids=[f"{k}={v!r}"[:40] for k, v, _ in BAD])
def test_every_bad_key_is_one_line_naming_file_and_key(tmp_path, key, value, message):
    doc = example_doc()
    _set(doc, key, value)
    p = tmp_path / "lab.toml"
    p.write_text(dumps_toml(doc))
    with pytest.raises(InputError) as err:
        load_instrument_config(p)
    line = str(err.value)
    assert "\n" not in line
    assert line.startswith(f"{p}: {message}"), line


@pytest.mark.parametrize("key", SCANNER_REQUIRED)
def test_each_safety_critical_scanner_key_is_required(tmp_path, key):
    doc = example_doc()
    del doc["scanner"][key]
    p = tmp_path / "lab.toml"
    p.write_text(dumps_toml(doc))
    with pytest.raises(InputError, match=rf"^{p}: scanner\.{key}: missing required key$"):
        load_instrument_config(p)


def test_not_toml_and_missing_file(tmp_path):
    p = tmp_path / "lab.toml"
    p.write_text("format = \n")
    with pytest.raises(InputError, match="not valid TOML"):
        load_instrument_config(p)
    with pytest.raises(InputError, match="no such file"):
        load_instrument_config(tmp_path / "absent.toml")


def test_the_value_types_check_themselves():
    d = load_instrument_config(EXAMPLE).daq
    with pytest.raises(ParamError, match="buffer_size"):
        DaqConfig(d.device, d.ao, d.ai, chunk_size=1000, lead_chunks=4, buffer_size=4999)
    with pytest.raises(ParamError, match="ai.lateral"):
        DaqConfig(d.device, d.ao, ("ai0", "ai0", "ai2"))
