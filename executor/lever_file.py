"""The lever in the instrument file: ``[cantilever]``, ``[friction]``, ``[baseline]`` and
``[calibration]``, read and (from ``nanoasm calibrate``) written.

``[cantilever]``
    The scene's keys (:class:`~nanoasm.world.params.CantileverParams`, checked by the same
    declaration): ``k`` (N/m), ``K_n`` (nm/V), ``C2`` (nm/V), ``lateral_gain`` (k_l K_l / h,
    nN/V) and ``alpha`` are required; ``C1`` (nm/V; default K_n h / l), ``length`` (l, nm),
    ``tip_height`` (h, nm) and ``signal_limit`` (V) are optional. The simulated detector's
    ``reflection_n``, ``reflection_l`` and ``signal_rms`` are refused: a real detector's
    baselines are the ``[baseline]`` maps. ``[cantilever.uncertainty]`` gives any of the
    keys' standard uncertainties (1σ, same units).
``[friction]``
    ``mu_ts``, the tip-substrate friction coefficient; ``[friction.uncertainty]`` likewise.
``[baseline]``
    The free-air baselines of eq. 3.28-3.29 at contact height: ``origin = [x, y]`` and
    ``side`` (nm, a square of the scanner frame) and the ``A`` and ``B`` maps (V, ``n``
    rows of ``n``, the top row first).
``[calibration]``
    Where ``nanoasm calibrate`` presses and slides (scanner nm): ``substrate = [x, y]``,
    ``flat``, ``slope`` and ``edge`` (lines ``[[x, y], [x, y]]``: on the substrate and up a
    sloped feature along the lever's y axis, onto a step along the lever axis),
    ``baseline_origin``, ``baseline_side``, ``baseline_pixels`` (default 16).

:func:`calibration_toml` writes the first three as ``nanoasm calibrate`` measured them,
to paste into the instrument file.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from nanoasm.instrument import InstrumentConfig
from nanoasm.param import ParamError, check_number, type_name
from nanoasm.schema import Table
from nanoasm.world.cantilever import Cantilever
from nanoasm.world.param_spec import from_table
from nanoasm.world.params import CantileverParams, FrictionParams

from .baselines import MAX_PIXELS, BaselineMaps
from .calibration import Calibration, CalibrationSites

#: ``[cantilever]`` keys of an instrument file, and those it must give.
LEVER_KEYS = ("k", "K_n", "C1", "C2", "lateral_gain", "alpha", "length", "tip_height", "signal_limit")
LEVER_REQUIRED = ("k", "K_n", "C2", "lateral_gain", "alpha")
#: The simulated detector's keys, which an instrument file refuses.
SIM_ONLY = ("reflection_n", "reflection_l", "signal_rms")


@dataclass(frozen=True, eq=False)
class InstrumentLever:
    """The lever an instrument file describes: the executor's compensation constants."""

    lever: Cantilever
    mu_ts: float | None = None
    uncertainty: dict[str, float] = dataclasses.field(default_factory=dict)  # "K_n", ..., "mu_ts" -> 1σ
    baselines: BaselineMaps | None = None


def _uncertainty(t: Table, keys) -> dict[str, float]:
    u = t.table("uncertainty", optional=True)
    if u is None:
        return {}
    u.check_keys(optional=keys)
    return {k: u.number(k, nonnegative=True) for k in keys if k in u}


def lever_from_tables(doc: Table) -> InstrumentLever | None:
    """The ``[cantilever]``, ``[friction]`` and ``[baseline]`` tables of an instrument
    document (None without ``[cantilever]``); each problem is one InputError line."""
    ct = doc.table("cantilever", optional=True)
    for name in ("friction", "baseline"):
        if ct is None and name in doc:
            doc.fail(name, "belongs to a lever: give the [cantilever] table too (nanoasm calibrate writes both)")
    if ct is None:
        return None
    for key in SIM_ONLY:
        if key in ct:
            ct.fail(key, "a simulated detector's key, not an instrument's: a real detector's baselines are "
                         "the [baseline] maps of nanoasm calibrate")
    ct.check_keys(required=LEVER_REQUIRED, optional=(*LEVER_KEYS, "uncertainty"))
    sigma = _uncertainty(ct, LEVER_KEYS)
    values = Table({k: v for k, v in ct.data.items() if k != "uncertainty"}, ct.source, ct.path)
    c = from_table(CantileverParams, values)
    try:
        lever = Cantilever(spring_constant=c.k, normal_gain=c.K_n, lateral_gain=c.lateral_gain,
                           tip_height=c.tip_height, lever_length=c.length, c2=c.C2,
                           c1_override=c.C1 if "C1" in ct else None, crosstalk=c.alpha, full_scale=c.signal_limit)
    except ValueError as e:
        raise ct.error(None, str(e)) from None
    mu = None
    ft = doc.table("friction", optional=True)
    if ft is not None:
        ft.check_keys(required=("mu_ts",), optional=("uncertainty",))
        mu = from_table(FrictionParams, Table({"mu_ts": ft.data["mu_ts"]}, ft.source, ft.path)).mu_ts
        sigma.update(_uncertainty(ft, ("mu_ts",)))
    bt = doc.table("baseline", optional=True)
    return InstrumentLever(lever, mu, sigma, None if bt is None else _baseline(bt, c.signal_limit))


def _map(t: Table, name: str, limit: float) -> np.ndarray:
    rows = t.array(name, min_len=1, max_len=MAX_PIXELS)
    n = len(rows)
    out = np.empty((n, n))
    for j, row in enumerate(rows, start=1):
        key = f"{name}[{j}]"
        if not isinstance(row, list) or len(row) != n:
            got = f"{len(row)} entries" if isinstance(row, list) else type_name(row)
            t.fail(key, f"must be a row of {n} numbers (a square map, as many rows as columns), got {got}")
        for i, v in enumerate(row, start=1):
            out[j - 1, i - 1] = check_number(v, lambda p, k=f"{key}[{i}]": t.fail(k, p), lo=-limit, hi=limit)
    return out


def _baseline(t: Table, limit: float) -> BaselineMaps:
    t.check_keys(required=("origin", "side", "A", "B"))
    origin = t.pair("origin", nonnegative=True)
    side = t.number("side", positive=True)
    a, b = _map(t, "A", limit), _map(t, "B", limit)
    try:
        return BaselineMaps(origin, side, a, b)
    except ParamError as e:
        raise t.error(e.key, e.problem) from None


def sites_from_table(doc: Table, scanner: InstrumentConfig) -> CalibrationSites | None:
    """The ``[calibration]`` table (None without one), checked against the scanner."""
    t = doc.table("calibration", optional=True)
    if t is None:
        return None
    lines = ("flat", "slope", "edge")
    t.check_keys(required=("substrate", *lines, "baseline_origin", "baseline_side"),
                 optional=("baseline_pixels",))
    got = {k: t.points(k, min_len=2) for k in lines}
    for k, pts in got.items():
        if len(pts) != 2:
            t.fail(k, f"must be a line of two points [[x, y], [x, y]], got {len(pts)} points")
    try:
        sites = CalibrationSites(t.pair("substrate"), got["flat"], got["slope"], got["edge"],
                                 t.pair("baseline_origin"), t.number("baseline_side", positive=True),
                                 t.integer("baseline_pixels", 16, lo=2, hi=MAX_PIXELS))
        sites.check(scanner)
    except ParamError as e:
        raise t.error(e.key, e.problem) from None
    return sites


# -- writing ---------------------------------------------------------------------------------

def _num(v: float, sigma: float | None = None) -> str:
    """A value with the digits its uncertainty warrants (two significant digits of σ, and
    at least four significant digits)."""
    digits = 6
    if sigma is not None and sigma > 0:
        digits = max(4, int(math.floor(math.log10(abs(v)) if v else 0) - math.floor(math.log10(sigma)) + 2))
    return repr(float(f"{v:.{digits}g}"))


def _two(sigma: float) -> str:
    """An uncertainty to two significant digits."""
    return repr(float(f"{sigma:.2g}"))


_NOTES = {"k": "N/m, given (the maker's or a thermal tune's): not measured here",
          "K_n": "nm/V, force curve contact slope (eq. 3.13)",
          "C1": "nm/V, K_n h / l (seed 3.6.3, an estimate)",
          "C2": "nm/V, where the tip climbs a step at several loads (eq. 3.30-3.34)",
          "lateral_gain": "nN/V, k_l K_l / h from the slope's friction loops (eq. 3.26-3.27)",
          "alpha": "S_l per volt of S_n while pressing (seed 3.5)",
          "length": "nm, l, given", "tip_height": "nm, h, given",
          "mu_ts": "the substrate loop's half-width per volt of S_n times (k_l K_l / h) / (k K_n)"}


def calibration_toml(cal: Calibration, what: str) -> str:
    """``[cantilever]``, ``[friction]`` and ``[baseline]`` as measured, each value with its
    standard uncertainty, ready to paste into the instrument file."""
    v = cal.values
    lines = [f"# The lever as `nanoasm calibrate` measured it {what}.",
             "# Paste these tables into the instrument file (nanoasm.instrument/1), replacing any there.",
             f"# The slope's own friction coefficient was {_num(v['mu_slope'].value, v['mu_slope'].sigma)} "
             f"± {v['mu_slope'].sigma:.2g} at a tilt of {v['tilt'].value:.3f} ± {v['tilt'].sigma:.2g} deg.",
             "", "[cantilever]"]
    keys = ("k", "K_n", "C1", "C2", "lateral_gain", "alpha")
    for k in keys:
        lines.append(f"{k} = {_num(v[k].value, v[k].sigma)}    # {_NOTES[k]}")
    for k in ("length", "tip_height"):
        lines.append(f"{k} = {_num(cal.given[k])}    # {_NOTES[k]}")
    lines += ["", "[cantilever.uncertainty]    # standard uncertainties (1 sigma, from the scatter of the fits), same units"]
    lines += [f"{k} = {_two(v[k].sigma)}" for k in keys if k != "k"]
    lines += ["", "[friction]", f"mu_ts = {_num(v['mu_ts'].value, v['mu_ts'].sigma)}    # {_NOTES['mu_ts']}",
              "", "[friction.uncertainty]", f"mu_ts = {_two(v['mu_ts'].sigma)}"]
    m = cal.baselines
    lines += ["", "[baseline]    # free-air baselines at contact height, eq. 3.28-3.29 (V; the top row first)",
              f"origin = [{_num(m.origin[0])}, {_num(m.origin[1])}]    # nm, the maps' lower-left corner",
              f"side = {_num(m.side)}    # nm"]
    for name, arr in (("A", m.a), ("B", m.b)):
        lines.append(f"{name} = [")
        lines += ["    [" + ", ".join(f"{x:.4f}" for x in row) + "]," for row in arr]
        lines.append("]")
    return "\n".join(lines) + "\n"


def lever_line(lever: Cantilever, maps: BaselineMaps | None) -> str:
    """The run's line on the lever it compensates with (a
    :class:`~nanoasm.world.cantilever.Cantilever`) and its baselines (``maps``, or None:
    measured in free air before each push)."""
    base = (f"{maps.pixels} x {maps.pixels} baseline maps" if maps is not None
            else "baselines measured in free air before each push")
    return (f"lever: K_n {lever.normal_gain:.4g} nm/V, C1 {lever.c1:.3g} nm/V, C2 {lever.c2:.4g} nm/V, k_l K_l / h "
            f"{lever.lateral_gain:.4g} nN/V, alpha {lever.crosstalk:.3g}; {base}")


__all__ = ["LEVER_KEYS", "LEVER_REQUIRED", "InstrumentLever", "calibration_toml", "lever_from_tables", "lever_line",
           "sites_from_table"]
