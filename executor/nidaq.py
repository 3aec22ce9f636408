"""An AFM driven through an NI DAQ card: the :class:`~nanoasm.instrument.Instrument`
protocol over the ``nidaqmx`` package.

What the lab's controller must do (the seed's own setup, ch. 3.2 and 5.4):

- The DAQ's AO channels drive the scanner's X and Y and the controller's Z command
  input (the setpoint line): ``[scanner] nm_per_volt`` maps each to nm. ``z = 0`` nm is
  the engage setpoint (the tip on the surface), ``z > 0`` lifts the tip by ``z``,
  ``z < 0`` presses it by ``-z`` (the push preload).
- The controller holds Z in tapping-mode feedback about that setpoint and puts its
  height (Z monitor) signal on an AI channel. Scans therefore only drive XY at
  ``z = 0`` and read the height channel: :meth:`NiDaqInstrument.scan_line` and
  :meth:`NiDaqInstrument.full_scan` travel lifted, engage, settle, scan, lift.
- The photodiode's S_n and S_l reach two more AI channels (the signal access module).
- When the backend starts, the DAC holds the rest output (where :meth:`park` leaves it;
  NI AO channels keep their last value when a task stops): the first stream holds
  :meth:`~nanoasm.instrument.InstrumentConfig.rest_codes`.

Streaming (see :mod:`nanoasm.executor.nidaq_stream`): ``write`` blocks until its chunk
has played and returns the S_n, S_l sampled on the same clock edges; between calls the
DAC holds the last sample. Instrument time is the DAQ's own count of played samples
divided by the sample rate, summed over the streams of a session. Use it as a context
manager: every exit parks the tip and closes the tasks::

    with NiDaqInstrument(load_instrument_config("lab.toml")) as inst:
        run(inst)
"""

from __future__ import annotations

from typing import Self

import numpy as np

from nanoasm.instrument import HeightImage, InstrumentConfig, Region, SignalBlock

from .feedback_scan import Raster, bin_mean, lift_in_place, park_path, scan_line_plan
from .instrument_file import InstrumentFile
from .nidaq_stream import DaqDriverNotFound, DaqStream, NiApi, NiDaqError
from .scan_args import count, scan_square, scanner_xy


class NiDaqInstrument:
    """The :class:`~nanoasm.instrument.Instrument` of an AFM behind an NI DAQ card.

    Parameters
    ----------
    config : InstrumentFile
        The loaded instrument file (:func:`~nanoasm.executor.instrument_file.load_instrument_config`).
    nidaqmx_module : module, optional
        The ``nidaqmx`` package, or a stand-in with the same API (tests); default: import it.

    Raises
    ------
    DaqDriverNotFound
        The NI-DAQmx driver is not installed.
    NiDaqError
        The package is missing, or the driver refused the device, a channel or the timing.
    """

    def __init__(self, config: InstrumentFile, *, nidaqmx_module=None):
        if not isinstance(config, InstrumentFile):
            raise TypeError(f"config must be an InstrumentFile, got {type(config).__name__}")
        if config.daq is None:
            raise TypeError(f"the instrument file is for backend = {config.backend!r}, not 'nidaq'")
        self.file = config
        self._api = NiApi.load(nidaqmx_module)
        self._last = config.scanner.rest_codes()
        self._t_offset = 0.0
        self._signals = (0.0, 0.0)
        self._stream: DaqStream | None = None
        self._open()

    # -- the Instrument protocol -----------------------------------------------------------------
    @property
    def config(self) -> InstrumentConfig:
        return self.file.scanner

    def clock(self) -> float:
        """Played samples over the sample rate, seconds since the first stream started."""
        generated = self._stream.generated() if self._stream is not None else 0
        return self._t_offset + generated / self.config.sample_rate

    def position(self) -> np.ndarray:
        return self._last.copy()

    def signals(self) -> tuple[float, float]:
        """The latest ``(S_n, S_l)`` in volts; after :meth:`park`, the last ones read."""
        if self._stream is not None:
            v = self._stream.latest()
            self._signals = (float(v[0]), float(v[1]))
        return self._signals

    def write(self, chunk: np.ndarray) -> SignalBlock:
        """Play an ``(n, 3)`` chunk of XYZ codes (checked first); S_n, S_l per sample."""
        t, ai = self._play(chunk)
        self._signals = (float(ai[0, -1]), float(ai[1, -1]))
        return SignalBlock(t, ai[0], ai[1])

    def scan_line(self, a: tuple[float, float], b: tuple[float, float], n: int) -> np.ndarray:
        """Heights (nm) at ``n`` points from ``a`` to ``b``: travel lifted, engage, settle,
        scan at ``[imaging] line_speed`` under the controller's feedback, lift."""
        n = count("n", n)
        im = self.file.imaging
        plan = scan_line_plan(self.config, self._last, scanner_xy(self.config, "a", a),
                              scanner_xy(self.config, "b", b), n,
                              im.line_speed, self._settle_samples())
        _, ai = self._play(plan.codes)
        return bin_mean(ai[2, plan.line] * im.height_nm_per_volt, plan.bins, n)

    def full_scan(self, pixels: int, region: Region | None = None) -> HeightImage:
        """A ``pixels`` x ``pixels`` image of the square of side max(width, height) at the
        region's lower-left corner (default: the largest square of the XY range at the
        origin), traced and retraced at ``[imaging] full_scan_speed``; the tip ends lifted."""
        pixels = count("pixels", pixels)
        x0, y0, side = scan_square(self.config, region)
        im = self.file.imaging
        raster = Raster(self.config, x0, y0, side, pixels, im.full_scan_speed)
        self._play(raster.approach(self._last, self._settle_samples()))
        height = np.empty((pixels, pixels))
        for i in range(pixels):
            row = raster.row(i)
            _, ai = self._play(row.codes)
            height[i] = bin_mean(ai[2, row.line] * im.height_nm_per_volt, row.bins, pixels)
        up = lift_in_place(self.config, self._last)
        if up.shape[0]:
            self._play(up)
        return HeightImage(height, raster.pixel_size, (x0, y0), source=f"nidaq:{self.file.daq.device}",
                           meta={"speed": im.full_scan_speed, "trace": "left to right, rows bottom up"})

    def park(self) -> None:
        """Lift Z to the top of its range in place, ramp XY to rest within the slew limit,
        wait until the DAC has played it, then stop and close the tasks.

        Idempotent: parked and closed, it does nothing. If the tasks were closed
        elsewhere than at rest (a failed earlier park), it opens a stream and parks.
        Raises :class:`NiDaqError` (after closing the tasks) if the DAQ fails meanwhile.
        """
        rest = self.config.rest_codes()
        if self._stream is None:
            if np.array_equal(self._last, rest):
                return
            self._open()
        try:
            self._last = self._stream.cancel()
            path = park_path(self.config, self._last)
            if path.shape[0]:
                self._play(path)
        finally:
            self._close()

    def close(self) -> None:
        """Park, and close the tasks whatever happens."""
        try:
            self.park()
        finally:
            if self._stream is not None:
                self._close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    # -- helpers -----------------------------------------------------------------------------------
    def _open(self) -> None:
        self._stream = DaqStream(self.file.daq, self.config, self._api, self._last)

    def _close(self) -> None:
        stream, self._stream = self._stream, None
        try:
            stream.close()
        finally:
            self._t_offset += stream.final_generated / self.config.sample_rate
            self._last = stream.tail.copy()

    def _play(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Play checked codes; returns the time of each sample and the ``(3, n)`` AI volts."""
        if self._stream is None:
            self._open()
        stream = self._stream
        try:
            start, ai = stream.play(codes)
        finally:
            self._last = stream.tail.copy()
        n = ai.shape[1]
        t = self._t_offset + (start + 1 + np.arange(n)) / self.config.sample_rate
        return t, ai

    def _settle_samples(self) -> int:
        return round(self.file.imaging.settle * self.config.sample_rate)


__all__ = ["DaqDriverNotFound", "NiDaqError", "NiDaqInstrument"]
