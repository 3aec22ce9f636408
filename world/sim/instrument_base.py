"""What the simulated instruments (:class:`~nanoasm.world.sim.SimulatedAFM` and
:class:`~nanoasm.world.sim.calibration_afm.CalibrationAFM`) share of the
:class:`~nanoasm.instrument.Instrument` protocol: the configuration, the clock and its
ledger, the last signals and DAC codes, and a write checked against the scanner's limits
before it is played (each plays its own way: ``_play``)."""

from __future__ import annotations

import numpy as np

from nanoasm.instrument import InstrumentConfig, SignalBlock, check_samples


class SimulatedInstrument:
    """The protocol's plain parts over ``params.scanner``, ``_clock``, ``_signals`` and
    ``_last`` (the last XYZ codes written), which a subclass keeps, and ``_play``."""

    @property
    def config(self) -> InstrumentConfig:
        return self.params.scanner

    def clock(self) -> float:
        """Instrument time in seconds (advances only by what the instrument does)."""
        return self._clock.now

    def ledger(self) -> dict[str, float]:
        """Instrument seconds per activity and their total (the report's ``instrument_time``)."""
        return self._clock.ledger()

    def signals(self) -> tuple[float, float]:
        """``(S_n, S_l)`` in volts at the last sample (raw: baselines, cross-talk, noise)."""
        return self._signals

    def position(self) -> np.ndarray:
        """The DAC's present XYZ codes: the last sample written; after a scan line its end,
        lifted; after a full scan or a calibration, the XY before it with Z raised to at
        least ``lift``."""
        return self._last.copy()

    def write(self, chunk: np.ndarray) -> SignalBlock:
        """Play ``(n, 3)`` XYZ codes at ``sample_rate`` after :func:`check_samples` (a refused
        chunk changes nothing)."""
        return self._play(check_samples(chunk, self.config, previous=self._last))

    def _play(self, codes: np.ndarray) -> SignalBlock:
        raise NotImplementedError
