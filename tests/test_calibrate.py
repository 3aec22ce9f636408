"""nanoasm calibrate (seed 3.4-3.6): the lever recovered through the instrument's own signals,
its tables pasted into the instrument file, and the baselines the push monitor uses."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from nanoasm.calibrate import simulated_calibration
from nanoasm.cli import main
from nanoasm.errors import InputError
from nanoasm.examples import path as example
from nanoasm.executor.calibration import CalibrationSetup, CalibrationSites, calibrate
from nanoasm.executor.engine import RunEngine
from nanoasm.executor.instrument_file import instrument_from_dict
from nanoasm.executor.lever_file import calibration_toml
from nanoasm.executor.monitor import PushMonitor
from nanoasm.world.families import family_case
from nanoasm.world.params import CantileverParams, FrictionParams, WorldParams
from nanoasm.world.scene import load_scene
from nanoasm.world.sim import SimulatedAFM
from nanoasm.world.sim.calibration_afm import CalibrationAFM

from simkit import push

#: The issue's lever: K_n = 61 nm/V, k_l K_l / h = 52 nN/V, mu = 0.12 (and C2, alpha off nominal too).
LEVER = WorldParams(cantilever=CantileverParams(K_n=61.0, lateral_gain=52.0, C2=27.0, alpha=0.12),
                    friction=FrictionParams(mu_ts=0.12))
TRUTH = {"K_n": 61.0, "lateral_gain": 52.0, "mu_ts": 0.12, "mu_slope": 0.12, "C2": 27.0, "alpha": 0.12}


def specimen_calibration(params: WorldParams, seed: int):
    inst = CalibrationAFM(params, seed=seed)
    s = inst.sites()
    centre = np.asarray(inst.config.xy_range) / 2
    sites = CalibrationSites(s["substrate"], s["flat"], s["slope"], s["edge"], tuple(centre - 5000.0), 10000.0)
    sites.check(inst.config)
    events = []
    cal = RunEngine(inst, [lambda topic, doc: events.append(doc.text) if topic == "event" else None]).run(
        calibrate(sites, CalibrationSetup(params.cantilever.k), inst.config))
    return cal, inst, events


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_simulated_lever_is_recovered_within_3_percent(seed):
    cal, inst, events = specimen_calibration(LEVER, seed)
    v = cal.values
    for key, truth in TRUTH.items():
        assert v[key].value == pytest.approx(truth, rel=0.03), key
        assert 0 < v[key].sigma and abs(v[key].value - truth) < 6 * v[key].sigma, key
    assert v["tilt"].value == pytest.approx(20.0, abs=0.1)
    # C1 is the seed's estimate K_n h / l from the measured K_n (the truth's 1.3 is not seen)
    assert v["C1"].value == pytest.approx(v["K_n"].value * 3000.0 / 200000.0)
    # one event line per step, and the tip parked at the end
    assert [e.split(" ")[0] for e in events] == ["force", "baselines:", "substrate", "slope", "edge:", "C1"]
    np.testing.assert_array_equal(inst.position(), inst.config.rest_codes())


@pytest.mark.parametrize("psi", [90.0, 37.0])
def test_the_lever_is_recovered_at_any_scan_angle(psi):
    """The lines follow the lever's axes, R(ψ)⁻¹ (eq. 3.7); diagonal ones too."""
    from dataclasses import replace

    from nanoasm.instrument import InstrumentConfig

    cal, _, _ = specimen_calibration(replace(LEVER, scanner=InstrumentConfig(scan_angle=psi)), 1)
    for key, truth in TRUTH.items():
        assert cal.values[key].value == pytest.approx(truth, rel=0.03), key


def test_the_seed_lever_gives_the_seeds_numbers():
    """The default world is the seed's lever: K_n = 89 nm/V, 37.8 nN/V, mu = 0.086 (§3.4)."""
    cal, _, _ = specimen_calibration(WorldParams(), 4)
    v = cal.values
    assert v["K_n"].value == pytest.approx(89.0, rel=0.005)
    assert v["lateral_gain"].value == pytest.approx(37.8, rel=0.02)
    assert v["mu_ts"].value == pytest.approx(0.086, rel=0.03)
    assert v["C2"].value == pytest.approx(23.0, rel=0.03)


def test_the_dry_run_calibration_of_a_family_recovers_its_drawn_lever_and_baselines():
    scene, _ = family_case("sparse", 5)
    c = scene.params.cantilever
    assert (c.K_n, c.lateral_gain) != (89.0, 37.8)          # the family drew its own lever
    sim = SimulatedAFM(scene, seed=5)
    cal = simulated_calibration(sim, 5)
    lever = cal.lever()
    assert lever.normal_gain == pytest.approx(c.K_n, rel=0.01)
    assert lever.lateral_gain == pytest.approx(c.lateral_gain, rel=0.03)
    assert lever.c2 == pytest.approx(c.C2, rel=0.03)
    assert lever.crosstalk == pytest.approx(c.alpha, abs=0.003)
    assert cal.values["mu_ts"].value == pytest.approx(scene.params.friction.mu_ts, rel=0.03)
    # the maps at contact height are the simulated detector's baselines there (reflection at
    # height 0, the bow across the scene's area), to a few mV
    m = cal.baselines
    n = m.pixels
    xs = m.origin[0] + m.side * np.arange(n) / (n - 1)
    a_true, b_true = sim._model.baselines(xs, np.zeros(n))
    np.testing.assert_allclose(m.a, np.broadcast_to(a_true, (n, n)), atol=0.01)
    np.testing.assert_allclose(m.b, np.broadcast_to(b_true, (n, n)), atol=0.01)
    # the simulated run itself is untouched: its clock has not moved
    assert sim.clock() == 0.0


def test_a_dry_run_compensates_with_the_calibrated_lever_not_the_truths():
    from nanoasm.dryrun import dry_run

    scene, layout = family_case("tiny", 2)
    events = []
    out = dry_run(scene, layout, subscribers=[lambda topic, doc: events.append(doc.text) if topic == "event" else None])
    truth, lever = scene.params.cantilever, out.calibration.lever()
    assert lever.normal_gain == pytest.approx(truth.K_n, rel=0.01) and lever.normal_gain != truth.K_n
    assert lever.c2 == pytest.approx(truth.C2, rel=0.03) and lever.c2 != truth.C2
    assert events[0] == (f"lever: K_n {lever.normal_gain:.4g} nm/V, C1 {lever.c1:.3g} nm/V, C2 {lever.c2:.4g} nm/V, "
                         f"k_l K_l / h {lever.lateral_gain:.4g} nN/V, alpha {lever.crosstalk:.3g}; 16 x 16 baseline maps")
    assert len(out.truly_filled) == len(layout.targets)


def test_generated_levers_vary_about_nominal_per_seed_and_the_examples_keep_the_seeds():
    from nanoasm.world.random_scene import LEVER_KEYS, SceneSpec, draw_lever, random_scene

    nominal = CantileverParams()
    levers = [family_case("sparse", seed)[0].params.cantilever for seed in (1, 2, 3)]
    assert levers[0] == family_case("sparse", 1)[0].params.cantilever        # deterministic per seed
    assert len({(c.K_n, c.C2, c.lateral_gain) for c in levers}) == 3
    for c in levers:
        for key in LEVER_KEYS:
            assert 0.8 <= getattr(c, key) / getattr(nominal, key) <= 1.2, key
    drawn = random_scene(SceneSpec(area=(2000.0, 2000.0), particles=3), 7).params.cantilever
    assert drawn == draw_lever(7) != nominal
    assert random_scene(SceneSpec(area=(2000.0, 2000.0), particles=3, lever_spread=0.0), 7).params.cantilever == nominal
    for name in ("bowtie", "particles", "rods", "mixed"):
        assert load_scene(example(f"{name}_scene.toml")).params.cantilever == nominal


def test_maps_remove_the_bias_of_a_free_air_baseline():
    """S̄n and S̄l of pushes on the substrate, against the simulated truth: the free air at
    the lift height biases S̄n by the reflection's change to contact (~0.2 V, ~2 nN); the
    calibration's maps do not (seed eq. 3.28-3.29)."""
    scene = load_scene(example("bowtie_scene.toml"))
    sim = SimulatedAFM(scene, seed=3)
    cal = simulated_calibration(sim, 3)
    cfg, model = sim.config, sim._model
    px, py = sim.placement
    bias = {"scalar": [], "maps": []}
    for sx, sy in [(4500, 600), (2500, 4700), (600, 2600)]:
        block, codes = push(sim, (px + sx, py + sy), (px + sx + 300, py + sy + 200))
        nm = cfg.codes_to_nm(codes)
        lifted, contact = np.abs(nm[:, 2] - cfg.lift) < 2.0, nm[:, 2] < 0     # travel at the lift height
        a, b = model.baselines(nm[:, 0], np.maximum(nm[:, 2], 0.0))
        sn_true = block.s_n - a
        sl_true = block.s_l - b - model.lever.crosstalk * sn_true
        for name, maps in (("scalar", None), ("maps", cal.baselines)):
            mon = PushMonitor(cfg.preload, lever=cal.lever(), baselines=maps)
            mon.set_baseline(block.s_n[lifted], block.s_l[lifted])
            sn, sl = mon.compensated(block.s_n[contact], block.s_l[contact], nm[contact, :2])
            bias[name].append((np.mean(sn - sn_true[contact]), np.mean(sl - sl_true[contact])))
    scalar, maps = np.array(bias["scalar"]), np.array(bias["maps"])
    assert np.all(np.abs(scalar[:, 0] - 0.207) < 0.01)              # 0.8 V (1 - exp(-300/1000))
    assert np.all(np.abs(maps) < 0.01)


def test_pasted_tables_load_with_their_uncertainties(tmp_path):
    cal, _, _ = specimen_calibration(LEVER, 1)
    text = calibration_toml(cal, "on a test")
    doc = tomllib.loads(example("instrument_ni.toml").read_text().split("\n# The lever the run")[0] + "\n" + text)
    f = instrument_from_dict(doc, "lab.toml")
    lv, v = f.lever.lever, cal.values
    assert lv.normal_gain == pytest.approx(v["K_n"].value, rel=1e-4)
    assert lv.lateral_gain == pytest.approx(v["lateral_gain"].value, rel=1e-3)
    assert lv.c2 == pytest.approx(v["C2"].value, rel=1e-3) and lv.c1 == pytest.approx(v["C1"].value, rel=1e-3)
    assert f.lever.mu_ts == pytest.approx(v["mu_ts"].value, rel=1e-3)
    assert set(f.lever.uncertainty) == {"K_n", "C1", "C2", "lateral_gain", "alpha", "mu_ts"}
    assert f.lever.uncertainty["lateral_gain"] == pytest.approx(v["lateral_gain"].sigma, rel=0.05)
    np.testing.assert_allclose(f.lever.baselines.a, cal.baselines.a, atol=6e-5)
    np.testing.assert_allclose(f.lever.baselines.b, cal.baselines.b, atol=6e-5)


def _doc(**tables) -> dict:
    doc = tomllib.loads(example("instrument_ni.toml").read_text())
    for path, value in tables.items():
        *head, last = path.split("__")
        t = doc
        for k in head:
            t = t.setdefault(k, {})
        if value is None:
            t.pop(last)
        else:
            t[last] = value
    return doc


BAD = [
    ({"cantilever__Kn": 61.0}, "cantilever.Kn: unknown key (did you mean 'K_n'?)"),
    ({"cantilever__C2": None}, "cantilever.C2: missing required key"),
    ({"cantilever__K_n": -3.0}, "cantilever.K_n: must be positive, got -3.0"),
    ({"cantilever__reflection_n": 0.8}, "cantilever.reflection_n: a simulated detector's key"),
    ({"cantilever__uncertainty": {"K_n": -1.0}}, "cantilever.uncertainty.K_n: must not be negative"),
    ({"cantilever__uncertainty": {"Kn": 1.0}}, "cantilever.uncertainty.Kn: unknown key (did you mean 'K_n'?)"),
    ({"friction__mu_t": 0.1}, "friction.mu_t: unknown key (did you mean 'mu_ts'?)"),
    ({"cantilever": None}, "friction: belongs to a lever"),
    ({"baseline": {"origin": [0, 0], "side": 100, "A": [[0.1, 0.2], [0.1]], "B": [[0, 0], [0, 0]]}},
     "baseline.A[2]: must be a row of 2 numbers"),
    ({"baseline": {"origin": [0, 0], "side": 100, "A": [[0.1, 0.2], [0.1, 0.2]], "B": [[0.0]]}},
     "baseline.B: must have the shape of A (2, 2), got (1, 1)"),
    ({"baseline": {"origin": [0, 0], "side": 100, "A": [[0.1, 20.0], [0.1, 0.2]], "B": [[0, 0], [0, 0]]}},
     "baseline.A[1][2]: must be at most 10"),
    ({"calibration__edge": [[55000, 30000], [55000, 29500]]}, "calibration.edge: must run along the lever's axis"),
    ({"calibration__slope": [[60000, 45300], [60000, 45250]]}, "calibration.slope: must be at least 200 nm long"),
    ({"calibration__substrate": [95000, 100]}, "calibration.substrate: (95000, 100) nm lies outside"),
    ({"calibration__flat": [[1, 2]]}, "calibration.flat: must have at least 2 entries"),
]


@pytest.mark.parametrize("tables, message", BAD, ids=[m.split(":")[0] for _, m in BAD])
def test_every_bad_lever_table_is_one_line_naming_file_and_key(tables, message):
    with pytest.raises(InputError) as err:
        instrument_from_dict(_doc(**tables), "lab.toml")
    assert str(err.value).startswith(f"lab.toml: {message}"), str(err.value)
    assert "\n" not in str(err.value)


def run(capsys, *args):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def test_calibrate_a_dry_run_scene_logs_each_step_writes_tables_and_plots(tmp_path, capsys):
    out, plots = tmp_path / "cal.toml", tmp_path / "plots"
    code, stdout, err = run(capsys, "calibrate", "--dry-run", example("particles_scene.toml"), "-o", out,
                            "--plot", plots)
    assert code == 0, err
    steps = [line for line in err.splitlines() if line.startswith("calibrate: ")]
    assert len(steps) == 6 and len(err.splitlines()) == 6
    assert stdout.startswith(f"{out}: written: K_n = 89.0") and f"{plots}: 5 plot(s) written" in stdout
    assert sorted(p.name for p in plots.iterdir()) == sorted(f"{n}.png" for n in (
        "force_curve", "baselines", "substrate_loop", "slope_loops", "edge"))
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in plots.iterdir())
    doc = tomllib.loads(out.read_text())
    assert set(doc) == {"cantilever", "friction", "baseline"}


@pytest.mark.parametrize("args, message", [
    ([], "--instrument/--dry-run: give exactly one"),
    (["--dry-run", "SCENE", "--instrument", "INST"], "--instrument/--dry-run: give exactly one"),
    (["--dry-run", "SCENE", "-o", "{d}/cal.json"], "output must end in .toml"),
    (["--dry-run", "SCENE", "--spring-constant", "-1"], "--spring-constant: must be positive"),
    (["--dry-run", "SCENE", "--plot", "{d}/no/such"], "--plot: folder"),
    (["--instrument", "INST"], "NI-DAQmx driver not found"),
    (["--instrument", "BARE"], "calibration: missing table"),
])
def test_calibrate_refuses_in_one_line(tmp_path, capsys, args, message):
    bare = tmp_path / "bare.toml"
    bare.write_text(example("instrument_ni.toml").read_text().split("\n# Where `nanoasm calibrate")[0])
    subs = {"SCENE": str(example("particles_scene.toml")), "INST": str(example("instrument_ni.toml")),
            "BARE": str(bare)}
    args = [subs.get(a, a.replace("{d}", str(tmp_path))) for a in args]
    if "-o" not in args:
        args += ["-o", str(tmp_path / "cal.toml")]
    code, _, err = run(capsys, "calibrate", *args)
    assert code == 1 and len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / "cal.toml").exists()


def test_run_needs_the_lever(tmp_path, capsys):
    inst = tmp_path / "lab.toml"
    inst.write_text(example("instrument_ni.toml").read_text().split("\n# The lever the run")[0])
    code, _, err = run(capsys, "run", example("bowtie.toml"), "--instrument", inst)
    assert code == 1 and err.strip() == (f"nanoasm: error: {inst}: cantilever: missing table: a run compensates the "
                                         "tip's deflection with the lever's constants; measure them with 'nanoasm "
                                         f"calibrate --instrument {inst} -o cal.toml' and paste its tables into the file")



class LeverOnSpecimen:
    """The fake DAQ's signals (``signal(ao_volts, index)``) of a lever pressing and sliding on
    the features the example instrument file's ``[calibration]`` names: flat substrate, a
    20° ramp under ``slope`` rising toward -y, a 50 nm step beyond x = 54700 nm under
    ``edge``. Scan angle 0: the lever's axis is -x, its y axis -y; the tip sits C2 S̄n
    along the axis from the piezo (eq. 3.30-3.34). Height channel: the surface, 250 nm/V."""

    def __init__(self, cfg, *, k=0.12, k_n=61.0, lateral_gain=52.0, mu=0.12, alpha=0.12, c2=27.0):
        self.cfg, self.k, self.k_n, self.lg, self.mu, self.alpha, self.c2 = cfg, k, k_n, lateral_gain, mu, alpha, c2
        self.prev, self.motion = None, np.zeros(2)
        self.tan = np.tan(np.radians(20.0))

    @staticmethod
    def on_ramp(xy):
        return (np.abs(xy[:, 0] - 60000.0) <= 300.0) & (xy[:, 1] >= 44600.0) & (xy[:, 1] <= 45400.0)

    def heights(self, xy):
        on_step = (xy[:, 0] >= 53000.0) & (xy[:, 0] <= 54700.0) & (np.abs(xy[:, 1] - 30000.0) <= 500.0)
        return np.where(on_step, 50.0, np.where(self.on_ramp(xy), self.tan * (45400.0 - xy[:, 1]), 0.0))

    def __call__(self, volts, index):
        from nanoasm.world.sim.calibration import slope_friction

        nm = self.cfg.volts_to_nm(volts.T)
        xy, z = nm[:, :2], nm[:, 2]
        prev = np.vstack([xy[:1] if self.prev is None else self.prev, xy[:-1]])
        self.prev = xy[-1:].copy()
        step = xy - prev
        ds = np.hypot(step[:, 0], step[:, 1])
        unit = step / np.where(ds > 0, ds, 1.0)[:, None]
        last = np.maximum.accumulate(np.where(ds > 0, np.arange(len(ds)), -1))
        motion = np.where((last >= 0)[:, None], unit[np.maximum(last, 0)], self.motion)   # held while still
        self.motion = motion[-1].copy()

        def tip(d):
            return xy + np.column_stack([-self.c2 * d / self.k_n, np.zeros_like(d)])

        h1 = self.heights(tip(np.maximum(-z, 0.0)))
        h = np.minimum(h1, self.heights(tip(np.maximum(h1 - z, 0.0))))
        d = np.maximum(h - z, 0.0)
        grade = np.where(self.on_ramp(tip(d)), -self.tan * motion[:, 1], 0.0)     # rising toward -y
        f = np.where(d > 0, slope_friction(self.k * d, grade, self.mu, self.mu * 10.0), 0.0)
        sn = d / self.k_n
        sl = f * motion[:, 1] / self.lg
        return np.vstack([sn + 0.5, sl + self.alpha * sn + 0.05, self.heights(xy) / 250.0])


def test_calibrate_through_the_ni_backend(monkeypatch, tmp_path, capsys):
    """``nanoasm calibrate --instrument`` drives the NI backend (its fake) through the
    Instrument protocol alone and recovers the lever behind it."""
    from nidaqmx_fake import FakeNidaqmx

    import nanoasm.run
    from nanoasm.executor.instrument_file import load_instrument_config
    from nanoasm.executor.nidaq import NiDaqInstrument

    doc = tomllib.loads(example("instrument_ni.toml").read_text())
    doc["scanner"]["sample_rate"] = 2000                 # fewer samples, the same procedure
    doc["daq"]["chunk_size"] = 100
    doc["calibration"].update(baseline_side=2000, baseline_pixels=4)     # a smaller map: fewer samples
    inst_file = tmp_path / "lab.json"
    inst_file.write_text(__import__("json").dumps(doc))
    cfg = load_instrument_config(inst_file).scanner
    fake = FakeNidaqmx(LeverOnSpecimen(cfg))
    monkeypatch.setattr(nanoasm.run, "open_hardware", lambda config: NiDaqInstrument(config, nidaqmx_module=fake))
    out = tmp_path / "cal.toml"
    code, stdout, err = run(capsys, "calibrate", "--instrument", inst_file, "-o", out)
    assert code == 0, err
    lever = tomllib.loads(out.read_text())
    c, f = lever["cantilever"], lever["friction"]
    assert c["K_n"] == pytest.approx(61.0, rel=0.01) and c["alpha"] == pytest.approx(0.12, abs=0.003)
    assert c["lateral_gain"] == pytest.approx(52.0, rel=0.03) and f["mu_ts"] == pytest.approx(0.12, rel=0.03)
    assert c["C2"] == pytest.approx(27.0, rel=0.03)
    assert all(t.closed for t in fake.tasks)             # parked and closed


def test_an_edge_fit_spoiled_into_a_negative_c2_fails_in_one_line():
    """A drift that jumps between the passes can turn the fitted slope round: that is a
    failed step (a dry-run then says so and compensates with the nominal lever), not a
    lever with C2 < 0 (an internal error in the dry-run at the scene limits before)."""
    from nanoasm.executor.calibration_fit import CalibrationFailed, edge_fit

    s_n = np.array([0.1, 0.3, 0.5, 0.6, 0.4, 0.2])       # loads in a palindrome-like order
    t = np.arange(6.0)
    with pytest.raises(CalibrationFailed, match="C2 came out -20 nm/V, not positive"):
        edge_fit(s_n, 100.0 + 20.0 * s_n, t)
    assert edge_fit(s_n, 100.0 - 20.0 * s_n, t).value == pytest.approx(20.0)


def test_the_calibration_specimen_refuses_a_scan_outside_the_range_as_an_instrument_limit():
    """As every instrument does (tests/test_instrument_conformance.py): a scan line with an
    end outside the scanner's range is an InstrumentLimitError, nothing scanned."""
    from nanoasm.errors import InstrumentLimitError
    from nanoasm.world.scene import load_scene
    from nanoasm.world.sim.afm import SimulatedAFM
    from nanoasm.world.sim.calibration_afm import CalibrationAFM

    inst = CalibrationAFM.beside(SimulatedAFM(load_scene(example("bowtie_scene.toml")), seed=1), 1)
    upper = inst.config.upper
    t0 = inst.clock()
    with pytest.raises(InstrumentLimitError, match="outside the scanner range; nothing scanned"):
        inst.scan_line((1000.0, 1000.0), (float(upper[0]) + 10.0, 1000.0), 16)
    assert inst.clock() == t0
