"""The simulated AFM: an :class:`~nanoasm.instrument.Instrument` over a scene's truth.

:class:`SimulatedAFM` (:mod:`.afm`) streams DAC chunks (:mod:`.stream`) through the
pushing physics (:mod:`.push`, :mod:`.push_support`, :mod:`.rods`, :mod:`.wire`) over the
objects' truth (:mod:`.objects`) and their contacts (:mod:`.contacts` on
:mod:`.contact_space`), with the signal model (:mod:`.signals`, :mod:`.calibration`), the
drift and creep truth (:mod:`.drift_model`), push faults (:mod:`.faults`) and the
instrument clock (:mod:`.clock`); its whole state as checked JSON for a resumed dry-run
(:mod:`.state`). :class:`~.calibration_afm.CalibrationAFM` is the same lever and detector
over a calibration specimen, which ``nanoasm calibrate --dry-run`` and every dry-run calibrate on. Only the dry-run harness, tests and benchmarks import
this package; the executor never does.
"""

from .afm import SimulatedAFM
from .calibration import ForceCurve, FrictionLoop
from .clock import InstrumentClock
from .drift_model import DriftModel
from .faults import PushFaults, draw_push_faults
from .signals import lever_from_params

__all__ = ["DriftModel", "ForceCurve", "FrictionLoop", "InstrumentClock", "PushFaults",
           "SimulatedAFM", "draw_push_faults", "lever_from_params"]
