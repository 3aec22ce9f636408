"""The preload a push needs to keep the tip down (seed eq. 4.7, 4.20): the closed form, the
spread it covers against draws like the world's, its limits, and a sticky particle that the
instrument's preload slips over and the chosen one pushes home."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from simkit import Events

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout
from nanoasm.dryrun import dry_run
from nanoasm.executor.contact_load import (ContactModel, needed_normal_force, preload_cap, push_point,
                                           push_preload)
from nanoasm.executor.dac_frames import PushLoad, deflection_offset
from nanoasm.executor.strategy import ExecOptions
from nanoasm.instrument import InstrumentConfig
from nanoasm.world.cantilever import SEED_LEVER
from nanoasm.world.params import AdhesionParams, FrictionParams, WorldParams
from nanoasm.world.pivot import rho
from nanoasm.world.scene import Scene

MODEL = ContactModel()


def _closed_form(f_os: float, r: float = 1.0, mu: float = 0.2, nu: float = 0.2, f_ts: float = 10.0) -> float:
    th = math.radians(20.0)
    return r * (mu + nu) * math.sin(th) / (math.cos(th) - r * mu * math.sin(th)) * f_os - f_ts


def test_the_nominal_force_is_eq_4_7_with_the_jkr_adhesion_and_eq_4_20_for_a_rod():
    p = Body("p", "particle", (0.0, 0.0), 90.0)
    f_os = 10.0 * (45.0 / 10.0) ** (4.0 / 3.0)            # JKR areas: (R_p / r_tip)^(4/3) F_ts
    assert needed_normal_force(p, 10.0, MODEL, 0.0) == pytest.approx(_closed_form(f_os), rel=1e-9)
    r = Body("r", "rod", (0.0, 0.0), 60.0, 0.0, 540.0)
    for l in (10.0, 54.0, 200.0):
        assert needed_normal_force(r, 10.0, MODEL, 0.0, l) == pytest.approx(
            _closed_form(200.0, float(rho(l, 540.0))), rel=1e-9)


def test_the_spread_covers_the_share_of_objects_it_says():
    """Draws like the world's (log-normal μos, ν and adhesion at 20, 20 and 30 %): the force
    at 2.5 σ is exceeded by about Φ(-2.5) = 0.6 % of objects (first order in the spreads)."""
    rng = np.random.default_rng(3)
    n = 200_000

    def lognormal(rel):
        s = math.sqrt(math.log1p(rel * rel))
        return np.exp(s * rng.standard_normal(n) - 0.5 * s * s)

    p = Body("p", "particle", (0.0, 0.0), 90.0)
    f_os = 10.0 * 4.5 ** (4.0 / 3.0) * lognormal(0.3)
    drawn = _closed_form(f_os, mu=0.2 * lognormal(0.2), nu=0.2 * lognormal(0.2))
    share = float(np.mean(drawn > needed_normal_force(p, 10.0, MODEL, 2.5)))
    assert 0.002 < share < 0.015
    assert float(np.mean(drawn > needed_normal_force(p, 10.0, MODEL, 0.0))) > 0.3


def test_the_push_point_is_measured_from_the_nearer_end():
    r = Body("r", "rod", (100.0, 100.0), 60.0, 90.0, 500.0)
    assert push_point(r, (130.0, 100.0 - 200.0)) == pytest.approx(50.0)
    assert push_point(r, (70.0, 100.0 + 240.0)) == pytest.approx(10.0)
    assert push_point(r, (100.0, 100.0 + 900.0)) == 0.0


@given(st.floats(-50.0, 500.0), st.floats(10.0, 400.0))
def test_the_preload_stays_within_the_instrument_and_presses_at_least_as_asked(force, preload):
    cfg = InstrumentConfig(preload=preload)
    d = push_preload(force, cfg, SEED_LEVER)
    cap = preload_cap(cfg, SEED_LEVER)
    assert cfg.preload <= d <= cap
    if d < cap:
        assert d * SEED_LEVER.spring_constant >= force - 1e-9
    assert push_preload(math.inf, cfg, SEED_LEVER) == cap
    # within the detector's full scale with room for the push's own forces (the DAC path
    # refuses a preload signal beyond it: 10.9 V once stopped a dry-run)
    assert PushLoad.from_preload(replace(cfg, preload=cap), SEED_LEVER).sn_bar <= 0.8 * SEED_LEVER.full_scale + 1e-9
    deflection_offset(PushLoad.from_preload(replace(cfg, preload=cap), SEED_LEVER), 0.0, SEED_LEVER)


def _sticky(options: ExecOptions):
    """A 120 nm particle stickier than the nominal model (μos = ν = 0.3, no scatter: F̄z
    16.7 nN where the instrument's 100 nm preload on the 0.12 N/m lever gives 12 nN) to be
    pushed 1.5 µm, with two particles beside it as drift references."""
    params = replace(WorldParams(), friction=FrictionParams(mu_os=0.3, nu=0.3, scatter=0.0),
                     adhesion=AdhesionParams(scatter=0.0))
    objects = (Body("a", "particle", (1000.0, 1500.0), 120.0), Body("b", "particle", (600.0, 2400.0), 60.0),
               Body("c", "particle", (2400.0, 600.0), 60.0))
    scene = Scene((3000.0, 3000.0), objects, (), params, 5)
    layout = Layout((3000.0, 3000.0), (Body("s1", "particle", (2500.0, 1500.0), 120.0),))
    events = Events()
    out = dry_run(scene, layout, options=options, subscribers=[events])
    return out, events


@pytest.mark.parametrize("sigmas, slips", [(2.5, False), (-1.0, True)])
def test_a_sticky_particle_is_pushed_without_the_tip_slipping_over_it(sigmas, slips):
    out, events = _sticky(ExecOptions(strategy="full", slip_sigmas=sigmas))
    slipped = [t for t in events.texts if "slipped" in t]
    assert bool(slipped) is slips, events.texts
    assert out.truly_filled == ("s1",) and not out.disagreements
