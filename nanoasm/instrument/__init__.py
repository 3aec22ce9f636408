"""The microscope as the executor sees it, implemented alike by the simulated AFM
(:mod:`nanoasm.world.sim`) and by the hardware backends (:mod:`nanoasm.executor.nidaq`,
:mod:`nanoasm.executor.nanonis`).

:class:`Instrument` is the protocol; :class:`InstrumentConfig` its ranges, calibration and
limits; :func:`check_samples` the limit check every DAC chunk passes before it is sent;
:func:`ramp` a chunk that moves within the slew limit; :class:`SignalBlock` what a chunk
reads back; :class:`HeightImage` the topography a full scan returns. This package imports
nothing of the world, the planner, the executor or the layouts.
"""

from .heightmap import HeightImage
from .protocol import AXES, Instrument, InstrumentConfig, Region, SignalBlock, check_samples, ramp

__all__ = ["AXES", "HeightImage", "Instrument", "InstrumentConfig", "Region", "SignalBlock",
           "check_samples", "ramp"]
