"""``nanoasm calibrate``: the lever's constants measured through the instrument (seed 3.4-3.6).

:func:`calibrate_instrument` runs :func:`~nanoasm.executor.calibration.calibrate` on the
hardware of an instrument file, at the places its ``[calibration]`` table names;
:func:`simulated_calibration` runs it on the simulated AFM's lever and detector over a
calibration specimen (:class:`~nanoasm.world.sim.calibration_afm.CalibrationAFM`: a flat
substrate, a 20° ramp, a step), which is what a dry-run compensates with: the truth's
constants never reach the executor. Both are run by the
:class:`~nanoasm.executor.engine.RunEngine`, which parks the tip however they end.
:func:`calibrate_files` is the command line's: the result as tables to paste into the
instrument file (:func:`~nanoasm.executor.lever_file.calibration_toml`), one line per
step on stderr, a plot per step (:mod:`nanoasm.calibration_plots`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from nanoasm.errors import InputError
from nanoasm.executor.calibration import Calibration, CalibrationSetup, CalibrationSites, calibrate
from nanoasm.executor.documents import EVENT, as_dict
from nanoasm.executor.engine import RunEngine

#: Cells per side of the baseline maps of a simulated calibration.
PIXELS = 16


def _events(out) -> list:
    """A subscriber printing each step's event line to ``out`` (None: nowhere)."""
    if out is None:
        return []

    def show(topic: str, doc) -> None:
        if topic == EVENT:
            print(f"calibrate: {as_dict(doc)['text']}", file=out, flush=True)
    return [show]


def simulated_calibration(sim, seed: int, side: float | None = None, *, out=None) -> Calibration:
    """Calibrate the lever and detector of the simulated AFM ``sim`` on a specimen beside it
    (:class:`~nanoasm.world.sim.calibration_afm.CalibrationAFM`, seeded by ``seed``), the
    maps over the square of ``side`` nm (default: the scene's larger side) centred in the
    scanner's range, where a run works. ``k``, ``h`` and ``l`` are given, as a user gives
    them; every other constant is measured. Step lines go to ``out`` if given."""
    from nanoasm.world.sim.calibration_afm import CalibrationAFM

    inst = CalibrationAFM.beside(sim, seed)
    cfg = inst.config
    side = float(max(sim.scene.area)) if side is None else float(side)
    origin = 0.5 * (np.asarray(cfg.xy_range, float) - side)
    s = inst.sites()
    sites = CalibrationSites(s["substrate"], s["flat"], s["slope"], s["edge"],
                             (float(origin[0]), float(origin[1])), side, PIXELS)
    c = sim.params.cantilever
    setup = CalibrationSetup(c.k, tip_height=c.tip_height, length=c.length, full_scale=c.signal_limit)
    return RunEngine(inst, _events(out)).run(calibrate(sites, setup, cfg))


def calibrate_instrument(config, spring_constant: float | None, *, out=None) -> Calibration:
    """Calibrate on the hardware of a loaded instrument file at its ``[calibration]`` sites."""
    from nanoasm.run import open_hardware

    if config.calibration is None:
        raise InputError(config.source, "calibration", "missing table: where the calibration presses and slides "
                                                       "(substrate, flat, slope, edge, baseline_origin, baseline_side)")
    lever = config.lever.lever if config.lever is not None else None
    k = spring_constant if spring_constant is not None else (lever.spring_constant if lever else None)
    if k is None:
        raise InputError(None, "--spring-constant", "is required (the lever's k in N/m, the maker's or a thermal "
                                                     "tune's) when the instrument file has no [cantilever] k")
    setup = CalibrationSetup(k, **({} if lever is None else {"tip_height": lever.tip_height,
                                                              "length": lever.lever_length,
                                                              "full_scale": lever.full_scale}))
    with open_hardware(config) as hardware:
        return RunEngine(hardware, _events(out)).run(calibrate(config.calibration, setup, hardware.config))


def _plot_dir(plot: Path | None) -> None:
    """Refuse a --plot that is a file, or whose folder is missing; need matplotlib."""
    if plot is None:
        return
    if plot.exists() and not plot.is_dir():
        raise InputError(str(plot), "--plot", "is a file; give a folder for the plots")
    if not plot.exists() and not (plot.parent if str(plot.parent) else Path(".")).is_dir():
        raise InputError(str(plot), "--plot", f"folder {str(plot.parent)!r} does not exist")
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise InputError(None, "--plot", "needs matplotlib: pip install 'nanoasm[bench]'") from None


def calibrate_files(output: Path, *, instrument: Path | None = None, scene: Path | None = None,
                    seed: int | None = None, spring_constant: float | None = None,
                    plot: Path | None = None) -> Calibration:
    """``nanoasm calibrate``: on the instrument file's hardware or on the simulated AFM of
    ``scene``; writes ``output`` (the tables to paste) and, with ``plot``, a plot per step."""
    from nanoasm.executor.lever_file import calibration_toml
    from nanoasm.fileio import write_atomic

    _plot_dir(plot)
    if scene is not None:
        from nanoasm.world.scene import load_scene
        from nanoasm.world.sim import SimulatedAFM

        sc = load_scene(scene)
        seed = (sc.seed or 0) if seed is None else seed
        cal = simulated_calibration(SimulatedAFM(sc, seed=seed), seed, out=sys.stderr)
        what = f"on the simulated AFM of {scene} (seed {seed})"
    else:
        from nanoasm.executor.instrument_file import load_instrument_config

        config = load_instrument_config(instrument)
        cal = calibrate_instrument(config, spring_constant, out=sys.stderr)
        what = f"on {config.name or instrument}"
    write_atomic(output, calibration_toml(cal, what))
    if plot is not None:
        from nanoasm.calibration_plots import plot_steps

        plot.mkdir(exist_ok=True)
        plot_steps(cal, plot)
    return cal


__all__ = ["calibrate_files", "calibrate_instrument", "simulated_calibration"]
