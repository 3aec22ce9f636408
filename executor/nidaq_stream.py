"""Two NI-DAQmx tasks that play checked DAC samples and read the signals on the same clock.

The AO task drives X, Y, Z: a continuous sample clock at ``[scanner] sample_rate``,
regeneration off (a sample is played once, never replayed from a stale buffer), and a
refill callback on ``register_every_n_samples_transferred_from_buffer_event``: every
``chunk_size`` samples that leave the buffer, it writes the next ``chunk_size`` with
``AnalogMultiChannelWriter.write_many_sample`` (a ``(3, n)`` float64 array of volts):
queued samples first, then the last one repeated. So the DAC always has
``lead_chunks * chunk_size`` samples ahead of it and holds still between commands; the
callback is the only writer once the stream runs.

The AI task (S_n, S_l, height) takes the AO sample clock (``/Dev1/ao/SampleClock``) as
its own and starts first, so AI sample ``k`` is converted on the clock edge that plays
AO sample ``k``; :meth:`DaqStream.play` returns exactly the AI samples of its chunk,
read by absolute index (``relative_to = FIRST_SAMPLE``, ``offset = k``). The AI buffer
overwrites unread samples: while nothing is playing nobody needs them.

Every chunk passes :func:`~nanoasm.instrument.check_samples` against the last
queued sample before it is queued; nothing else reaches the DAQ. Errors of the driver
become one-line :class:`NiDaqError`\\ s.
"""

from __future__ import annotations

import importlib
import threading
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nanoasm.errors import NanoasmError
from nanoasm.instrument import InstrumentConfig, check_samples

from .instrument_file import TERMINALS, DaqConfig

#: DAQmx read offsets are int32.
MAX_OFFSET = 2**31 - 1


class NiDaqError(NanoasmError):
    """The NI-DAQmx driver or device failed; ``str(err)`` is one line."""


class DaqDriverNotFound(NiDaqError):
    """The nidaqmx package is there, the NI-DAQmx driver is not."""

    def __init__(self) -> None:
        super().__init__("NI-DAQmx driver not found: install NI-DAQmx or use nanoasm dry-run")


def one_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message, with its DAQmx error code."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[0] if lines else type(exc).__name__
    code = getattr(exc, "error_code", None)
    return f"{text} (error {code})" if code is not None else text


@dataclass(frozen=True)
class NiApi:
    """The parts of the ``nidaqmx`` package the stream uses (a fake module in tests)."""

    Task: Any
    constants: Any
    errors: Any
    Writer: Any
    Reader: Any

    @classmethod
    def load(cls, module: Any = None) -> NiApi:
        """Resolve ``module`` (default: import ``nidaqmx``) into the API the stream needs."""
        if module is None:
            try:
                module = importlib.import_module("nidaqmx")
            except ImportError:
                raise NiDaqError("the nidaqmx package is not installed: pip install nidaqmx and install "
                                 "NI-DAQmx, or use nanoasm dry-run") from None
        part = {name: getattr(module, name, None) or importlib.import_module(f"{module.__name__}.{name}")
                for name in ("constants", "errors", "stream_writers", "stream_readers")}
        return cls(module.Task, part["constants"], part["errors"],
                   part["stream_writers"].AnalogMultiChannelWriter,
                   part["stream_readers"].AnalogMultiChannelReader)

    @contextmanager
    def translated(self, doing: str):
        """Turn the driver's exceptions into one-line :class:`NiDaqError`\\ s."""
        errors = self.errors
        try:
            yield
        except errors.DaqNotFoundError:
            raise DaqDriverNotFound() from None
        except getattr(errors, "DaqNotSupportedError", ()) as exc:
            raise NiDaqError(f"NI-DAQmx is not supported here: {one_line(exc)}; use nanoasm dry-run") from None
        except errors.Error as exc:
            raise NiDaqError(f"NI-DAQmx failed {doing}: {one_line(exc)}") from None


@dataclass(eq=False)
class _Queued:
    codes: np.ndarray  # (n, 3) int64, checked
    done: int = 0  # samples of it already written


@dataclass(eq=False)
class _Ring:
    """The codes written at the last ``size`` stream indices: what the DAC held when it stopped."""

    size: int
    codes: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.codes = np.zeros((self.size, 3), np.int64)

    def put(self, first: int, codes: np.ndarray) -> None:
        idx = (first + np.arange(codes.shape[0])) % self.size
        self.codes[idx] = codes

    def at(self, index: int) -> np.ndarray:
        return self.codes[index % self.size].copy()


class DaqStream:
    """An open AO + AI stream holding the DAC at ``hold`` (codes) until told otherwise.

    Parameters
    ----------
    daq, scanner : DaqConfig, InstrumentConfig
        Channels and stream sizes; range, calibration, limits and sample rate.
    api : NiApi
        The driver (``NiApi.load()`` for the real one).
    hold : (3,) int codes
        The DAC's present output; the stream starts by holding it.
    """

    def __init__(self, daq: DaqConfig, scanner: InstrumentConfig, api: NiApi, hold: np.ndarray):
        self.daq, self.scanner, self.api = daq, scanner, api
        self._lock = threading.Lock()
        self._queue: deque[_Queued] = deque()
        self._pending = 0  # queued samples not yet written
        self._written = 0  # samples written to the AO buffer: the index of the next one
        self._ring = _Ring(daq.buffer_size + daq.chunk_size)
        self.tail = np.asarray(hold, np.int64).reshape(3).copy()  # last sample queued
        self._sent = self.tail.copy()  # last sample written to the AO buffer
        self._fault: BaseException | None = None
        self._ao = self._ai = None
        self.closed = False
        self.final_generated = 0
        try:
            with api.translated("opening the DAQ tasks"):
                self._open()
        except BaseException:
            self._close_tasks()
            self.closed = True
            raise

    # -- opening --------------------------------------------------------------------------------
    def _open(self) -> None:
        c, d, s = self.api.constants, self.daq, self.scanner
        self._ao = self.api.Task()
        for ch in d.ao:
            self._ao.ao_channels.add_ao_voltage_chan(d.physical(ch), min_val=s.volt_range[0],
                                                     max_val=s.volt_range[1])
        self._ao.timing.cfg_samp_clk_timing(s.sample_rate, sample_mode=c.AcquisitionType.CONTINUOUS,
                                            samps_per_chan=d.buffer_size)
        self._ao.out_stream.regen_mode = c.RegenerationMode.DONT_ALLOW_REGENERATION
        self._ao.register_every_n_samples_transferred_from_buffer_event(d.chunk_size, self._refill)
        self._writer = self.api.Writer(self._ao.out_stream, auto_start=False)

        self._ai = self.api.Task()
        terminal = getattr(c.TerminalConfiguration, TERMINALS[d.terminal])
        for ch, (lo, hi) in zip(d.ai, (d.signal_range, d.signal_range, d.height_range)):
            self._ai.ai_channels.add_ai_voltage_chan(d.physical(ch), terminal_config=terminal,
                                                     min_val=lo, max_val=hi)
        self._ai.timing.cfg_samp_clk_timing(s.sample_rate, source=d.clock_terminal,
                                            sample_mode=c.AcquisitionType.CONTINUOUS,
                                            samps_per_chan=d.buffer_size)
        self._ai.in_stream.overwrite = c.OverwriteMode.OVERWRITE_UNREAD_SAMPLES
        self._reader = self.api.Reader(self._ai.in_stream)

        lead = d.lead_chunks * d.chunk_size
        prefill = np.repeat(self.tail.reshape(1, 3), lead, axis=0)
        self._writer.write_many_sample(self._volts(prefill), timeout=d.timeout)
        self._ring.put(0, prefill)
        self._written = lead
        self._ai.start()  # armed: it waits for the AO sample clock
        self._ao.start()

    def _volts(self, codes: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(self.scanner.codes_to_volts(codes).T, dtype=np.float64)

    # -- the refill callback (DAQmx's thread) ------------------------------------------------------
    def _refill(self, task_handle, event_type, number_of_samples, callback_data) -> int:
        """Write the next ``number_of_samples``; after any failure write nothing more, so the
        AO task underflows and stops and the DAC keeps the last sample it played."""
        if self._fault is not None:
            return 0
        try:
            with self._lock:
                codes, taken = self._next(int(number_of_samples))
                self._writer.write_many_sample(self._volts(codes), timeout=self.daq.timeout)
                self._commit(codes, taken)
        except Exception as exc:  # noqa: BLE001 - never into the driver's thread: play() reports it
            self._fault = exc
        return 0

    def _next(self, n: int) -> tuple[np.ndarray, list[tuple[_Queued, int]]]:
        """The next ``n`` samples, queued ones first, then the last one held; nothing consumed."""
        out = np.empty((n, 3), np.int64)
        taken: list[tuple[_Queued, int]] = []
        k = 0
        for q in self._queue:
            if k == n:
                break
            m = min(n - k, q.codes.shape[0] - q.done)
            out[k:k + m] = q.codes[q.done:q.done + m]
            taken.append((q, m))
            k += m
        out[k:] = out[k - 1] if k else self._sent
        return out, taken

    def _commit(self, codes: np.ndarray, taken: list[tuple[_Queued, int]]) -> None:
        """Record a block the driver accepted."""
        for q, m in taken:
            q.done += m
            self._pending -= m
        while self._queue and self._queue[0].done == self._queue[0].codes.shape[0]:
            self._queue.popleft()
        self._ring.put(self._written, codes)
        self._written += codes.shape[0]
        self._sent = codes[-1].copy()

    # -- playing ----------------------------------------------------------------------------------
    def play(self, codes: np.ndarray) -> tuple[int, np.ndarray]:
        """Queue a chunk, wait until it has played, return its first stream index and the
        ``(3, n)`` AI volts (S_n, S_l, height) sampled with it.

        The chunk is checked against the last queued sample first; a refused chunk leaves
        nothing queued. If anything interrupts the wait (Ctrl-C, a driver error) the
        unsent rest is dropped and the DAC holds the last sample written (:attr:`tail`).
        """
        if self.closed:
            raise NiDaqError("the DAQ stream is closed")
        c = check_samples(codes, self.scanner, previous=self.tail)
        self._raise_fault()
        with self._lock:
            start = self._written + self._pending
            if start + c.shape[0] > MAX_OFFSET:
                raise NiDaqError("the DAQ stream has run 2**31 samples, the limit of DAQmx read offsets: "
                                 "park and resume")
            self._queue.append(_Queued(c))
            self._pending += c.shape[0]
            self.tail = c[-1].copy()
        try:
            return start, self._read(start, c.shape[0])
        except BaseException:
            self.cancel()
            raise

    def cancel(self) -> np.ndarray:
        """Drop every queued sample not yet written; returns the sample the DAC will hold."""
        with self._lock:
            self._queue.clear()
            self._pending = 0
            self.tail = self._sent.copy()
        return self.tail.copy()

    def _read(self, first: int, n: int) -> np.ndarray:
        out = np.empty((3, n))
        step = self.daq.chunk_size
        for k in range(0, n, step):
            m = min(step, n - k)
            buf = np.empty((3, m))
            ahead = max(0, first + k + m - self.generated()) / self.scanner.sample_rate
            self._read_at(buf, first + k, m, self.daq.timeout + ahead)
            out[:, k:k + m] = buf
            self._raise_fault()
        return out

    def _read_at(self, buf: np.ndarray, first: int, m: int, timeout: float) -> None:
        c, errors = self.api.constants, self.api.errors
        try:
            self._ai.in_stream.relative_to = c.ReadRelativeTo.FIRST_SAMPLE
            self._ai.in_stream.offset = first
            self._reader.read_many_sample(buf, m, timeout)
        except errors.Error as exc:
            self._raise_fault()
            cause: BaseException = exc
            try:
                self._ao.is_task_done()  # raises the AO task's own error if it stopped on one
            except errors.Error as ao_exc:
                cause = ao_exc
            raise NiDaqError(f"the DAQ stream stopped: {one_line(cause)}") from None

    def _raise_fault(self) -> None:
        if self._fault is not None:
            raise NiDaqError(f"the DAQ stream stopped: refilling the AO buffer failed: {one_line(self._fault)}")

    # -- state --------------------------------------------------------------------------------------
    def generated(self) -> int:
        """Samples per channel the DAC has played in this stream (the DAQ's own counter)."""
        if self.closed:
            return self.final_generated
        with self.api.translated("reading the AO sample count"):
            return int(self._ao.out_stream.total_samp_per_chan_generated)

    def latest(self) -> np.ndarray:
        """The most recent AI sample, ``(3,)`` volts: S_n, S_l, height."""
        if self.closed:
            raise NiDaqError("the DAQ stream is closed")
        c = self.api.constants
        buf = np.empty((3, 1))
        with self.api.translated("reading the AI channels"):
            self._ai.in_stream.relative_to = c.ReadRelativeTo.MOST_RECENT_SAMPLE
            self._ai.in_stream.offset = -1
            self._reader.read_many_sample(buf, 1, self.daq.timeout)
        return buf[:, 0].copy()

    # -- closing --------------------------------------------------------------------------------------
    def close(self) -> np.ndarray:
        """Stop and close both tasks; returns the codes the DAC holds (the last sample it played).

        Idempotent. Raises :class:`NiDaqError` after closing everything if the driver
        failed to stop or close a task.
        """
        if self.closed:
            return self.tail.copy()
        self.cancel()
        first = self._close_tasks()
        self.closed = True
        if first is not None:
            raise NiDaqError(f"NI-DAQmx failed closing the DAQ tasks: {one_line(first)}")
        return self.tail.copy()

    def _close_tasks(self) -> BaseException | None:
        """Stop AO (the DAC keeps its last played sample), note where it stopped, stop AI, close both."""
        first: BaseException | None = None
        tasks = [t for t in (self._ao, self._ai) if t is not None]
        for i, task in enumerate(tasks):
            try:
                task.stop()
            except Exception as exc:  # noqa: BLE001 - stop and close every task, report the first failure
                first = first or exc
            if i == 0 and task is self._ao:
                self._note_stop()
        for task in tasks:
            try:
                task.close()
            except Exception as exc:  # noqa: BLE001 - as above
                first = first or exc
        return first

    def _note_stop(self) -> None:
        try:
            g = int(self._ao.out_stream.total_samp_per_chan_generated)
        except Exception:  # noqa: BLE001 - the device is gone
            return  # the device is gone: the last sample written is the best knowledge
        self.final_generated = g
        if 0 < g <= self._written and g > self._written - self._ring.size:
            self.tail = self._ring.at(g - 1)
