"""The Nanonis backend at its TCP boundary: the real nanonis-spm client against a fake
controller (tests/nanonis_fake.py) that speaks the documented protocol and records
every call."""

from __future__ import annotations

import math
import sys
import tomllib

import numpy as np
import pytest
from nanonis_fake import FakeNanonis

from nanoasm.errors import InputError, InstrumentLimitError, NanoasmError
from nanoasm.examples import path as example_path
from nanoasm.executor.instrument_file import instrument_from_dict
from nanoasm.executor.nanonis import NanonisError, NanonisInstrument
from nanoasm.executor.nanonis_path import legs, simplify
from nanoasm.instrument import Instrument, ramp

pytest.importorskip("nanonis_spm")

EXAMPLE = example_path("instrument_nanonis.toml")
SETS = {"ZCtrl.OnOffSet", "ZCtrl.ZPosSet", "ZCtrl.SetpntSet", "FolMe.XYPosSet", "FolMe.SpeedSet",
        "Scan.FrameSet", "Scan.BufferSet", "Scan.SpeedSet", "Scan.Action"}


def doc(port: int = 6501, **nanonis) -> dict:
    d = tomllib.loads(EXAMPLE.read_text())
    d["nanonis"].update({"port": port, "scan_channel": 3, "timeout": 2.0, **nanonis})
    d["imaging"]["settle"] = 0.0
    return d


@pytest.fixture
def fake():
    with FakeNanonis() as f:
        f.buffer = ([3], 64, 64)
        yield f


def open_inst(fake, **nanonis) -> NanonisInstrument:
    return NanonisInstrument(instrument_from_dict(doc(fake.port, **nanonis), "lab.toml"))


def nanonis_xy(inst, xy):
    """Nanonis metres of a scanner-frame point (nm), with the file's centre."""
    half = np.asarray(inst.config.xy_range) / 2
    return (np.asarray(xy, float) - half + np.asarray(inst.net.centre)) * 1e-9


def assert_parked(inst, fake, surface=1e-6):
    cfg = inst.config
    rest = cfg.codes_to_nm(cfg.rest_codes())
    assert not fake.on
    assert fake.z == pytest.approx(surface + cfg.z_range / 2 * 1e-9, abs=1e-10)
    np.testing.assert_allclose((fake.x, fake.y), nanonis_xy(inst, rest[:2]), atol=1e-12)
    np.testing.assert_array_equal(inst.position(), cfg.rest_codes())
    assert fake.violations == []


# -- the instrument file -------------------------------------------------------------------------------

def test_the_example_loads_and_nidaq_stays_the_default():
    f = instrument_from_dict(doc(), "lab.toml")
    assert f.backend == "nanonis" and f.daq is None and f.nanonis.address == "localhost:6501"
    ni = tomllib.loads(example_path("instrument_ni.toml").read_text())
    assert "backend" not in ni and instrument_from_dict(ni, "ni.toml").backend == "nidaq"


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["nanonis"].update(prot=1), "nanonis.prot: unknown key (did you mean 'port'?)"),
    (lambda d: d["nanonis"].pop("host"), "nanonis.host: missing required key"),
    (lambda d: d["nanonis"].update(port=70000), "nanonis.port: must be at most 65535"),
    (lambda d: d["nanonis"].update(lateral=0), "nanonis.lateral: signal 0 is already normal"),
    (lambda d: d["nanonis"].update(scan_channel=24), "nanonis.scan_channel: must be at most 23"),
    (lambda d: d["nanonis"].update(host="my host"), "nanonis.host: must be a host name"),
    (lambda d: d["nanonis"].update(leg=0), "nanonis.leg: must be positive"),
    (lambda d: d.pop("nanonis"), "nanonis: missing required table"),
    (lambda d: d.update(backend="ni"), "backend: must be one of 'nidaq', 'nanonis'"),
    (lambda d: d.update(daq={"device": "Dev1"}), "daq: not a table of backend = 'nanonis'"),
    (lambda d: d["imaging"].update(height_nm_per_volt=250), "imaging.height_nm_per_volt: not used by backend"),
])
def test_a_bad_nanonis_file_is_one_line(edit, message):
    d = doc()
    edit(d)
    with pytest.raises(InputError) as err:
        instrument_from_dict(d, "lab.toml")
    assert str(err.value).startswith(f"lab.toml: {message}"), str(err.value)


def test_a_nidaq_file_refuses_a_nanonis_table():
    d = tomllib.loads(example_path("instrument_ni.toml").read_text())
    d["nanonis"] = {"host": "localhost"}
    with pytest.raises(InputError, match=r"^ni.toml: nanonis: not a table of backend = 'nidaq'"):
        instrument_from_dict(d, "ni.toml")


# -- opening -----------------------------------------------------------------------------------------------

def test_opening_takes_the_surface_then_parks(fake):
    inst = open_inst(fake, centre=[-1000.0, 500.0])
    with inst:
        assert isinstance(inst, Instrument)
        assert fake.names()[:6] == ["ZCtrl.LimitsGet", "ZCtrl.OnOffGet", "Scan.StatusGet", "Piezo.RangeGet",
                                    "ZCtrl.ZPosGet", "FolMe.XYPosGet"]
        assert_parked(inst, fake)
        zs = [a[0] for c, a in fake.calls if c == "ZCtrl.ZPosSet"]
        assert np.all(np.diff(zs) > 0) and max(np.diff(zs)) <= 20e-9 * (1 + 1e-6)   # z_step
    assert_parked(inst, fake)


def test_a_setpoint_is_set_before_the_surface_is_taken(fake):
    with open_inst(fake, setpoint=0.8):
        names = fake.names()
        assert names.index("ZCtrl.SetpntSet") < names.index("ZCtrl.ZPosGet")
        assert fake.setpoint == pytest.approx(0.8)


def test_a_withdrawn_tip_is_refused_and_nothing_moves():
    with FakeNanonis(engaged=False) as fake:
        with pytest.raises(NanonisError, match=r"^the Nanonis Z controller is off: engage the tip"):
            open_inst(fake)
        assert not SETS & set(fake.names())


def test_a_z_range_beyond_the_controller_limits_is_refused_and_nothing_moves():
    with FakeNanonis(z_limits=(2e-6, -5e-6)) as fake:      # surface at 1 µm: the top, 3 µm, is beyond
        with pytest.raises(NanonisError, match=r"z_range = 4000 nm about the surface at Z = 1000 nm leaves "
                                               r"the controller's Z limits \[-5000, 2000\] nm"):
            open_inst(fake)
        assert not SETS & set(fake.names())


def test_a_frame_beyond_the_piezo_range_is_refused_and_nothing_moves(fake):
    with pytest.raises(NanonisError, match=r"reaches ±\(51000, 45000\) nm, beyond the piezo's XY range "
                                           r"±\(50000, 50000\) nm"):
        open_inst(fake, centre=[6000.0, 0.0])       # 45 µm about 6 µm: past the fake's ±50 µm
    assert not SETS & set(fake.names())
    with open_inst(fake, centre=[5000.0, 0.0]):     # 45 µm about 5 µm: just within
        assert fake.violations == []


def test_a_tip_outside_the_scanner_frame_is_refused():
    with FakeNanonis(xy=(46e-6, 0.0)) as fake:
        with pytest.raises(NanonisError, match=r"the tip is at Nanonis XY \(46000, 0\) nm, outside"):
            open_inst(fake)
        assert not SETS & set(fake.names())


def test_an_unreachable_controller_is_one_line():
    with FakeNanonis() as fake:
        port = fake.port
    with pytest.raises(NanonisError) as err:
        NanonisInstrument(instrument_from_dict(doc(port), "lab.toml"))
    line = str(err.value)
    assert line.startswith(f"cannot reach the Nanonis controller at localhost:{port}: ") and "\n" not in line


def test_missing_package_is_one_line(monkeypatch, fake):
    monkeypatch.setitem(sys.modules, "nanonis_spm", None)
    with pytest.raises(NanonisError, match=r"^the nanonis-spm package is not installed: pip install"):
        open_inst(fake)
    assert fake.calls == []


# -- streamed paths ----------------------------------------------------------------------------------------

def push_path(inst, dx=600.0, z=-100.0):
    """Lower at the present XY to z, push dx in x, lift to lift: within the slew limit."""
    cfg = inst.config
    here = inst.position()
    a = cfg.codes_to_nm(here)
    a[2] = z
    b = a.copy()
    b[0] += dx
    c = b.copy()
    c[2] = cfg.lift
    pa, pb, pc = (cfg.nm_to_codes(p) for p in (a, b, c))
    return np.vstack([ramp(here, pa, cfg), ramp(pa, pb, cfg, speed=2000.0), ramp(pb, pc, cfg)])


def test_a_push_is_follow_me_legs_with_the_controller_off(fake):
    with open_inst(fake) as inst:
        cfg = inst.config
        inst_start = inst.position()
        codes = push_path(inst)
        start = len(fake.calls)
        block = inst.write(codes)
        calls = fake.calls[start:]
        names = [c for c, _ in calls]
        assert "ZCtrl.OnOffSet" not in names and all(not on for *_, on in fake.track[start:])
        moves = [a for c, a in calls if c == "FolMe.XYPosSet"]
        assert all(a[2] == 1 for a in moves)                        # wait for the end of each move
        xs = np.array([a[0] for a in moves])
        end = cfg.codes_to_nm(codes[-1])
        pushed = end[0] - cfg.codes_to_nm(inst_start)[0]           # 600 nm within a DAC code
        assert len(moves) == math.ceil(pushed / 50) and np.all(np.diff(xs) * 1e9 <= 50 + 1e-6)   # leg
        np.testing.assert_allclose(xs[-1], nanonis_xy(inst, end[:2])[0], atol=1e-12)
        speeds = [a[0] for c, a in calls if c == "FolMe.SpeedSet"]
        assert speeds and max(speeds) <= cfg.max_speed * 1e-9 * (1 + 1e-6)
        plan = legs(cfg.codes_to_nm(inst_start), cfg.codes_to_nm(codes), float(cfg.nm_per_code.max()), 50, 1000)
        assert names.count("Signals.ValsGet") == len(plan) > len(moves)     # a read a leg, Z legs too
        reads = [i for i, n in enumerate(names) if n == "Signals.ValsGet"]
        zs = [a[0] for c, a in calls if c == "ZCtrl.ZPosSet"]
        assert max(np.abs(np.diff(zs))) <= 20e-9 * (1 + 1e-6)        # z_step
        assert all(b - a <= 5 for a, b in zip(reads, reads[1:]))      # at most 50 nm of Z apart in contact
        # pressed 100 nm below the surface: S_n is the deflection at 89 nm/V, lifted it is zero
        assert block.s_n[-1] == 0.0 and np.any(np.isclose(block.s_n, 100 / 89, rtol=1e-4))
        assert len(block) == len(codes) and np.all(np.diff(block.t) >= 0)
        np.testing.assert_array_equal(inst.position(), codes[-1])
        assert fake.z == pytest.approx(1e-6 + cfg.lift * 1e-9, abs=1e-10) and fake.violations == []


def test_chunks_beyond_the_limits_send_nothing(fake):
    with open_inst(fake) as inst:
        here = inst.position()
        start = len(fake.calls)
        for bad in (np.array([[here[0] + 2000, here[1], here[2]]]), np.array([[np.nan, 0, 0]]),
                    np.array([[here[0], here[1], -1]])):
            with pytest.raises(InstrumentLimitError):
                inst.write(bad)
        for call in (lambda: inst.scan_line((-1.0, 0.0), (10.0, 0.0), 5),
                     lambda: inst.full_scan(16, (89000.0, 0.0, 90000.0, 5000.0))):
            with pytest.raises(InstrumentLimitError, match="nothing sent"):
                call()
        assert len(fake.calls) == start


# -- scans -----------------------------------------------------------------------------------------------

def bump_scanner_xy(inst):
    """Scanner-frame nm of the fake's bump at Nanonis (2, 2) µm."""
    return np.array([2000.0, 2000.0]) + np.asarray(inst.config.xy_range) / 2 - np.asarray(inst.net.centre)


def test_scan_line_is_engaged_point_by_point_and_ends_lifted(fake):
    with open_inst(fake) as inst:
        bx, by = bump_scanner_xy(inst)
        start = len(fake.calls)
        h = inst.scan_line((bx - 1000, by), (bx + 1000, by), 21)
        calls = fake.calls[start:]
        on = [i for i, (c, a) in enumerate(calls) if c == "ZCtrl.OnOffSet" and a == (1,)]
        off = [i for i, (c, a) in enumerate(calls) if c == "ZCtrl.OnOffSet" and a == (0,)]
        assert len(on) == len(off) == 1 and on[0] < off[0]
        engaged = calls[on[0]:off[0]]
        assert sum(c == "FolMe.XYPosSet" for c, _ in engaged) == 20
        assert sum(c == "ZCtrl.ZPosGet" for c, _ in engaged) == 1 + 21      # engaged, then each point
        assert [a[0] for c, a in engaged if c == "FolMe.SpeedSet"] == [pytest.approx(2000e-9)]
        assert h.shape == (21,) and np.argmax(h) == 10 and h[10] == pytest.approx(40.0, abs=0.01)
        assert abs(h[0]) < 0.01
        cfg = inst.config
        np.testing.assert_array_equal(inst.position(), cfg.nm_to_codes(np.array([bx + 1000, by, cfg.lift])))
        assert not fake.on and fake.violations == []


@pytest.mark.parametrize("pixels", [32, 40])      # 40: the fake scan module makes it 32; resampled
def test_full_scan_images_the_frame_in_the_scanner_frame(fake, pixels):
    with open_inst(fake) as inst:
        bx, by = bump_scanner_xy(inst)
        img = inst.full_scan(pixels, (bx - 1000, by - 1000, bx + 1000, by + 1000))
        assert img.shape == (pixels, pixels) and img.pixel_size == pytest.approx(2000 / pixels)
        assert img.origin == (bx - 1000, by - 1000)
        i, j = np.unravel_index(np.argmax(img.height), img.shape)
        xs, ys = img.pixel_centres()
        assert math.hypot(xs[j] - bx, ys[i] - by) < img.pixel_size
        assert img.height.max() == pytest.approx(40.0, abs=3.0) and np.percentile(img.height, 10) < 1.0
        names = fake.names()
        frame = next(a for c, a in fake.calls if c == "Scan.FrameSet")
        np.testing.assert_allclose(frame[:4], [2e-6, 2e-6, 2e-6, 2e-6], atol=1e-12)
        assert fake.calls[names.index("Scan.BufferSet")][1] == ([3], pixels, pixels)
        assert fake.calls[names.index("Scan.Action")][1] == (0, 1)    # start, upwards
        assert inst.position()[2] >= inst.config.nm_to_codes(np.array([0, 0, inst.config.lift]))[2]
        assert not fake.on and fake.violations == []


def test_a_downward_frame_is_flipped(fake):
    with open_inst(fake) as inst:
        bx, by = bump_scanner_xy(inst)
        fake.surface = lambda x, y: 1e-6 + (20e-9 if y > 2.5e-6 else 0.0)   # a step up at Nanonis y = 2.5 µm
        fake._scan_orig = fake._scan
        fake._scan = lambda name, a: fake._scan_orig(name, [a[0], 0] if name == "Scan.Action" else a)
        img = inst.full_scan(32, (bx - 1000, by - 1000, bx + 1000, by + 1000))
        _, ys = img.pixel_centres()
        upper = ys > by + 500
        assert np.all(img.height[upper] > 15) and np.all(img.height[~upper] < 5)


def test_pushes_follow_the_surface_the_scan_lines_find(fake):
    with open_inst(fake) as inst:
        def pressed_to():
            start = len(fake.calls)
            inst.write(push_path(inst, dx=100.0))
            return min(a[0] for c, a in fake.calls[start:] if c == "ZCtrl.ZPosSet")

        fake.surface = lambda x, y: 1e-6 + 10e-9                      # the sample drifted 10 nm up
        h = inst.scan_line((40000.0, 40000.0), (41000.0, 40000.0), 11)
        assert h == pytest.approx(np.full(11, 10.0), abs=0.01)       # against the surface before
        assert pressed_to() == pytest.approx(1e-6 + 10e-9 - 100e-9, abs=1e-10)
        fake.surface = lambda x, y: 1e-6 + 60e-9                      # 50 nm more: an object under the line
        inst.scan_line((40000.0, 40000.0), (41000.0, 40000.0), 11)
        assert pressed_to() == pytest.approx(1e-6 + 10e-9 - 100e-9, abs=1e-10)   # not taken for the surface


# -- failures and parking ----------------------------------------------------------------------------------

def test_a_refused_command_is_one_line_and_park_still_parks(fake):
    inst = open_inst(fake)
    fake.refuse_next("FolMe.XYPosSet", "Follow Me is busy\nsecond line")
    with pytest.raises(NanonisError) as err:
        inst.write(push_path(inst))
    assert str(err.value) == "the Nanonis controller refused FolMe.XYPosSet: Follow Me is busy"
    inst.close()
    assert_parked(inst, fake)
    assert fake.connections == 1


@pytest.mark.parametrize("how", ["hang_up_next", "silent_next"])
def test_a_lost_controller_is_one_line_and_park_reconnects(fake, how):
    inst = open_inst(fake, timeout=0.3)
    getattr(fake, how)("FolMe.XYPosSet")
    with pytest.raises(NanonisError) as err:
        inst.write(push_path(inst))
    line = str(err.value)
    assert line.startswith("FolMe.XYPosSet: ") and "\n" not in line
    assert ("lost the Nanonis controller" if how == "hang_up_next" else "no reply") in line
    inst.close()
    assert fake.connections == 2
    assert_parked(inst, fake)


@pytest.mark.parametrize("exit_by", ["normal", RuntimeError, KeyboardInterrupt])
def test_the_context_manager_parks_on_every_exit(fake, exit_by):
    inst = open_inst(fake)
    with pytest.raises(exit_by) if exit_by != "normal" else _nothing(), inst:
        inst.write(push_path(inst)[:150])           # left pressed into the surface
        assert fake.z < 1e-6
        if exit_by != "normal":
            raise exit_by()
    assert_parked(inst, fake)
    n = len(fake.calls)
    inst.park()                                     # idempotent once parked
    assert len(fake.calls) == n


def test_ctrl_c_in_a_reply_parks_from_where_the_tip_is(fake, monkeypatch):
    inst = open_inst(fake)
    link = inst._link
    real = link._client.FolMe_XYPosSet

    def interrupted(*args):
        real(*args)
        raise KeyboardInterrupt

    monkeypatch.setattr(link._client, "FolMe_XYPosSet", interrupted)
    with pytest.raises(KeyboardInterrupt), inst:
        inst.write(push_path(inst))
    assert fake.connections == 2
    assert_parked(inst, fake)


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


# -- the path as legs --------------------------------------------------------------------------------------

def test_simplify_keeps_corners_and_drops_collinear_samples():
    t = np.linspace(0, 1, 11)[:, None]
    path = np.vstack([t * [100, 0, 0], [100, 0, 0] + t[1:] * [0, 100, 0]])
    keep = simplify(path, 0.5)
    assert keep.tolist() == [0, 10, 20]
    wobble = path + np.where(np.arange(len(path)) == 5, 2.0, 0.0)[:, None] * [0, 1, 0]
    assert 5 in simplify(wobble, 0.5).tolist() and 5 not in simplify(wobble, 3.0).tolist()


def test_legs_are_short_where_the_tip_reaches_the_surface():
    start = np.array([0.0, 0.0, 300.0])
    k = np.arange(1, 101)[:, None] / 100
    lifted = start + k * [1000, 0, 0]
    pressed = np.array([1000.0, 0.0, -100.0]) + k * [1000, 0, 0]
    lower = np.array([[1000.0, 0.0, 100.0], [1000.0, 0.0, -100.0]])   # 400 nm in Z in two samples
    out = legs(start, np.vstack([lifted, lower, pressed]), 0.5, 100.0, 400.0)
    assert [lg.samples for lg in out] == [33, 34, 33, 1, 1] + [10] * 10
    assert out[0].first == 0 and out[-1].stop == 202 and all(a.stop == b.first for a, b in zip(out, out[1:]))
    np.testing.assert_allclose(out[-1].target, [2000, 0, -100])


def test_the_backend_is_a_nanoasm_error_family():
    assert issubclass(NanonisError, NanoasmError)


# -- the command line --------------------------------------------------------------------------------------

def test_run_help_names_both_backends(capsys):
    from nanoasm.cli import main

    assert main(["run", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "nidaq (NI-DAQmx, the default) or nanonis (Nanonis TCP)" in out


def _instrument_file(tmp_path, port: int):
    from nanoasm.fileio import dumps_toml

    p = tmp_path / "nanonis.toml"
    p.write_text(dumps_toml(doc(port)))
    return p


def test_run_on_an_unreachable_controller_is_one_line(capsys, tmp_path):
    from nanoasm.cli import main

    with FakeNanonis() as gone:
        port = gone.port
    code = main(["run", str(example_path("bowtie.toml")), "--instrument", str(_instrument_file(tmp_path, port)),
                 "--report", str(tmp_path / "r.json")])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err and "Traceback" not in err
    assert err.startswith(f"nanoasm: error: cannot reach the Nanonis controller at localhost:{port}")
    assert not (tmp_path / "r.json").exists()


def test_nanoasm_run_goes_through_the_controller_and_parks(capsys, tmp_path, fake):
    """The whole run on a bare substrate (nothing to push): full scan, scan lines, park."""
    from nanoasm.cli import main

    code = main(["run", str(example_path("bowtie.toml")), "--instrument", str(_instrument_file(tmp_path, fake.port)),
                 "--report", str(tmp_path / "r.json")])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "0 of 7 slot(s) filled" in out and (tmp_path / "r.json").exists()
    names = fake.names()
    assert names.count("Scan.Action") == 2 and "FolMe.XYPosSet" in names
    assert not fake.on and fake.violations == [] and fake.connections == 1
    assert fake.z == pytest.approx(1e-6 + 2000e-9, abs=1e-10)          # parked: the top of z_range 4000


def test_resample_keeps_a_plane_at_the_new_pixel_centres():
    from nanoasm.executor.scan_args import resample

    rows, cols = 40, 48                                  # 40 asked, the scan module's 48 columns
    y, x = (np.arange(rows) + 0.5) / rows, (np.arange(cols) + 0.5) / cols
    frame = 10.0 * x[None, :] + 3.0 * y[:, None]
    out = resample(frame, 40)
    u = (np.arange(40) + 0.5) / 40
    np.testing.assert_allclose(out, 10.0 * u[None, :] + 3.0 * u[:, None], atol=1e-9)
    assert resample(out, 40) is out
