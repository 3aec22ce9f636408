"""A stand-in for the ``nidaqmx`` package at the boundary the NI backend uses.

:class:`FakeNidaqmx` has the attributes the backend reads from the real module
(``Task``, ``constants``, ``errors``, ``stream_writers.AnalogMultiChannelWriter``,
``stream_readers.AnalogMultiChannelReader``) and simulates one device behind them:

- an AO buffer played one sample per clock edge, regeneration off: when the buffer
  runs dry the AO task stops with an underflow error, as the hardware does;
- the every-N-samples-transferred callback after each N samples played;
- AI samples taken on the AO sample clock only when the AI task's clock source is
  ``/<dev>/ao/SampleClock`` and only while the AI task runs (an AI started after the
  AO misses the first samples); each AI sample is ``signal(ao_volts, index)`` of the
  AO sample played on the same edge;
- reads by absolute index (``FIRST_SAMPLE`` + ``offset``) or ``MOST_RECENT_SAMPLE``.

The device advances only while the caller waits in a read, by as many samples as the
wait needs and at most ``timeout * rate`` (then a timeout error), so tests are
deterministic and single-threaded. Everything is recorded: ``tasks`` (channels,
timing, stream settings, start/stop/close order in ``log``), ``writes`` (every array
handed to ``write_many_sample``) and ``played`` (every AO sample the DAC put out).
"""

from __future__ import annotations

import enum
import math
from types import SimpleNamespace

import numpy as np


class AcquisitionType(enum.Enum):
    FINITE = 10178
    CONTINUOUS = 10123


class RegenerationMode(enum.Enum):
    ALLOW_REGENERATION = 10097
    DONT_ALLOW_REGENERATION = 10158


class TerminalConfiguration(enum.Enum):
    RSE = 10083
    NRSE = 10078
    DIFF = 10106
    PSEUDO_DIFF = 12529
    DEFAULT = -1


class OverwriteMode(enum.Enum):
    OVERWRITE_UNREAD_SAMPLES = 10252
    DO_NOT_OVERWRITE_UNREAD_SAMPLES = 10159


class ReadRelativeTo(enum.Enum):
    FIRST_SAMPLE = 10424
    CURRENT_READ_POSITION = 10425
    MOST_RECENT_SAMPLE = 10428


class Error(Exception):
    pass


class DaqNotFoundError(Error):
    pass


class DaqNotSupportedError(Error):
    pass


class DaqError(Error):
    def __init__(self, message, error_code, task_name=""):
        super().__init__(f"{message}\nTask Name: {task_name}\n\nStatus Code: {error_code}")
        self.error_code = error_code


TIMEOUT, UNDERFLOW, INVALID_TASK, OVERWRITTEN = -200284, -200290, -200088, -200279


def default_signal(volts: np.ndarray, index: np.ndarray) -> np.ndarray:
    """S_n, S_l, height from the AO volts (x, y, z) of the same clock edge."""
    x, y, z = volts
    return np.vstack([0.5 * z + 0.01 * x, 0.25 * x - 0.1 * y, 0.2 * z])


class _Channels:
    def __init__(self, task, kind):
        self.task, self.kind = task, kind

    def add_ao_voltage_chan(self, physical_channel, name_to_assign_to_channel="", min_val=-10.0,
                            max_val=10.0, units=None, custom_scale_name=""):
        self.task._add("ao", {"physical": physical_channel, "min_val": min_val, "max_val": max_val})

    def add_ai_voltage_chan(self, physical_channel, name_to_assign_to_channel="",
                            terminal_config=TerminalConfiguration.DEFAULT, min_val=-5.0, max_val=5.0,
                            units=None, custom_scale_name=""):
        self.task._add("ai", {"physical": physical_channel, "terminal": terminal_config,
                                  "min_val": min_val, "max_val": max_val})
        fail = self.task.fake.fail_channel
        if fail is not None and physical_channel == fail:
            raise DaqError(f"Physical channel specified does not exist on this device.\n"
                           f"Channel Name: {physical_channel}", -200170)


class _Timing:
    def __init__(self, task):
        self.task = task

    def cfg_samp_clk_timing(self, rate, source="", active_edge=None, sample_mode=AcquisitionType.FINITE,
                            samps_per_chan=1000):
        self.task._check()
        self.task.timing_args = {"rate": rate, "source": source, "sample_mode": sample_mode,
                                     "samps_per_chan": samps_per_chan}
        self.task.log.append("timing")


class _OutStream:
    def __init__(self, task):
        self._task = task
        self.regen_mode = RegenerationMode.ALLOW_REGENERATION

    @property
    def total_samp_per_chan_generated(self):
        self._task._check()
        return self._task.generated


class _InStream:
    def __init__(self, task):
        self._task = task
        self.overwrite = OverwriteMode.DO_NOT_OVERWRITE_UNREAD_SAMPLES
        self.relative_to = ReadRelativeTo.CURRENT_READ_POSITION
        self.offset = 0


class FakeTask:
    """One task: AO (x, y, z) or AI (normal, lateral, height), decided by its channels."""

    def __init__(self, fake, name):
        self.fake, self.name = fake, name
        self.kind = None
        self.channels: list[dict] = []
        self.ao_channels, self.ai_channels = _Channels(self, "ao"), _Channels(self, "ai")
        self.timing = _Timing(self)
        self.out_stream, self.in_stream = _OutStream(self), _InStream(self)
        self.timing_args: dict | None = None
        self.event: tuple[int, object] | None = None
        self.log: list[str] = []
        self.running = self.closed = False
        self.error: DaqError | None = None
        self.buffer: list[np.ndarray] = []  # AO: (3, n) blocks not yet played
        self.generated = 0  # AO: samples played; AI: samples acquired
        self.acquired: list[np.ndarray] = []  # AI: (3, n) blocks

    def _check(self):
        if self.closed:
            raise DaqError("Task specified is invalid or does not exist.", INVALID_TASK, self.name)

    def _add(self, kind, chan):
        self._check()
        if self.kind not in (None, kind):
            raise DaqError("Cannot mix AI and AO channels in one task.", -200559, self.name)
        self.kind = kind
        self.channels.append(chan)
        self.log.append(f"add_{kind}")

    def register_every_n_samples_transferred_from_buffer_event(self, sample_interval, callback_method):
        self._check()
        if self.running:
            raise DaqError("Register events before starting the task.", -200960, self.name)
        self.event = (int(sample_interval), callback_method)
        self.log.append("register")

    def start(self):
        self._check()
        if self.kind == "ao" and self.buffered() == 0:
            raise DaqError("No samples written before start with regeneration off.", -200462, self.name)
        self.running = True
        self.log.append("start")
        self.fake.starts.append(self)

    def stop(self):
        self._check()
        self.running = False
        self.buffer.clear()
        self.log.append("stop")

    def close(self):
        self._check()
        self.running = False
        self.closed = True
        self.log.append("close")

    def is_task_done(self):
        self._check()
        if self.error is not None:
            raise self.error
        return not self.running

    def buffered(self) -> int:
        return sum(b.shape[1] for b in self.buffer)

    # -- the device: one AO task drives the clock ------------------------------------------------
    def play_block(self) -> bool:
        """Play the next N samples (N: the event interval); False after an underflow."""
        n = self.event[0] if self.event else max(1, self.buffered())
        if not self.running or self.error is not None:
            return False
        if self.buffered() < n:
            self.error = DaqError("Output underflow: the generation stopped because no samples were "
                                  "available (regeneration is off).", UNDERFLOW, self.name)
            self.running = False
            return False
        block = np.hstack(self.buffer)
        volts, rest = block[:, :n], block[:, n:]
        self.buffer = [rest] if rest.shape[1] else []
        index = self.generated + np.arange(n)
        self.generated += n
        self.fake.played.append(volts.T.copy())
        for ai in self.fake.tasks:
            if ai.kind == "ai" and ai.running and ai.clocked_by(self):
                ai.acquired.append(self.fake.signal(volts, index))
                ai.generated += n
        if self.event:
            self.event[1](id(self), 2, n, None)
        return True

    def clocked_by(self, ao) -> bool:
        dev = ao.channels[0]["physical"].split("/")[0]
        return (self.timing_args or {}).get("source") == f"/{dev}/ao/SampleClock"


class _Writer:
    def __init__(self, out_stream, auto_start=None):
        self.task = out_stream._task
        self.auto_start = auto_start
        self.task.fake.writers.append(self)

    def write_many_sample(self, data, timeout=10.0):
        task, fake = self.task, self.task.fake
        task._check()
        fake.write_calls += 1
        if fake.fail_write_call is not None and fake.write_calls == fake.fail_write_call:
            raise DaqError("The device was removed or disconnected.", -201003, task.name)
        if not (isinstance(data, np.ndarray) and data.dtype == np.float64 and data.flags.c_contiguous
                and data.ndim == 2 and data.shape[0] == len(task.channels)):
            raise DaqError(f"Write data must be a C-contiguous float64 (n_channels, n) array, got "
                           f"{getattr(data, 'dtype', type(data))} {getattr(data, 'shape', '')}", -200524,
                           task.name)
        lo = np.array([c["min_val"] for c in task.channels])[:, None]
        hi = np.array([c["max_val"] for c in task.channels])[:, None]
        if not np.all(np.isfinite(data)) or np.any(data < lo) or np.any(data > hi):
            raise DaqError("Requested value is not a supported value for this property.", -200561, task.name)
        space = task.timing_args["samps_per_chan"] - task.buffered()
        if data.shape[1] > space:
            raise DaqError("Write cannot be performed: the buffer is full and the timeout expired.",
                           -200292, task.name)
        task.buffer.append(data.copy())
        fake.writes.append(data.copy())
        return data.shape[1]


class _Reader:
    def __init__(self, in_stream):
        self.task = in_stream._task

    def read_many_sample(self, data, number_of_samples_per_channel=-1, timeout=10.0):
        task, fake = self.task, self.task.fake
        task._check()
        fake.reads += 1
        if fake.interrupt_read is not None and fake.reads == fake.interrupt_read:
            raise KeyboardInterrupt
        n = int(number_of_samples_per_channel)
        if data.shape != (len(task.channels), n) or data.dtype != np.float64 or not data.flags.c_contiguous:
            raise DaqError(f"Read buffer has the wrong shape {data.shape}", -200229, task.name)
        if not task.running:
            raise DaqError("The task is not running.", -200474, task.name)
        s = task.in_stream
        if s.relative_to is ReadRelativeTo.MOST_RECENT_SAMPLE:
            if task.generated == 0:
                self._wait(1, timeout)
            first = task.generated + s.offset
        elif s.relative_to is ReadRelativeTo.FIRST_SAMPLE:
            first = s.offset
        else:
            raise DaqError("the fake reads FIRST_SAMPLE or MOST_RECENT_SAMPLE only", -1, task.name)
        self._wait(first + n, timeout)
        acquired = np.hstack(task.acquired)
        size = task.timing_args["samps_per_chan"]
        if first < task.generated - size:
            raise DaqError("Samples no longer available: they were overwritten.", OVERWRITTEN, task.name)
        data[:] = acquired[:, first:first + n]
        return n

    def _wait(self, needed: int, timeout: float) -> None:
        task, fake = self.task, self.task.fake
        budget = math.ceil(timeout * fake.rate()) if fake.rate() else 0
        ao = fake.ao_task()
        edges = ao.generated if ao is not None else 0  # the clock runs whether or not AI sees it
        while task.generated < needed:
            if ao is None or ao.generated - edges >= budget or not ao.play_block():
                raise DaqError("Wait Until Done did not indicate all samples were acquired: "
                               "the timeout expired.", TIMEOUT, task.name)


class FakeNidaqmx:
    """The fake module. ``signal(volts (3, n), index (n,)) -> (3, n)`` makes the AI samples."""

    __name__ = "nidaqmx_fake"

    def __init__(self, signal=default_signal):
        self.signal = signal
        self.constants = SimpleNamespace(
            AcquisitionType=AcquisitionType, RegenerationMode=RegenerationMode,
            TerminalConfiguration=TerminalConfiguration, OverwriteMode=OverwriteMode,
            ReadRelativeTo=ReadRelativeTo)
        self.errors = SimpleNamespace(Error=Error, DaqError=DaqError, DaqNotFoundError=DaqNotFoundError,
                                      DaqNotSupportedError=DaqNotSupportedError)
        self.stream_writers = SimpleNamespace(AnalogMultiChannelWriter=_Writer)
        self.stream_readers = SimpleNamespace(AnalogMultiChannelReader=_Reader)
        self.tasks: list[FakeTask] = []
        self.writers: list[_Writer] = []
        self.starts: list[FakeTask] = []
        self.writes: list[np.ndarray] = []
        self.played: list[np.ndarray] = []
        self.write_calls = self.reads = 0
        self.fail_write_call: int | None = None  # this write_many_sample call raises
        self.interrupt_read: int | None = None  # this read raises KeyboardInterrupt
        self.fail_channel: str | None = None  # adding this AI channel raises
        self.task_error: type[Exception] | None = None  # Task() raises this

    def Task(self, new_task_name=""):
        if self.task_error is not None:
            raise self.task_error("Could not find an installation of NI-DAQmx.")
        task = FakeTask(self, new_task_name or f"_unnamedTask<{len(self.tasks)}>")
        self.tasks.append(task)
        return task

    # -- inspection ------------------------------------------------------------------------------
    def ao_task(self) -> FakeTask | None:
        live = [t for t in self.tasks if t.kind == "ao" and not t.closed]
        return live[-1] if live else None

    def rate(self) -> float:
        ao = self.ao_task()
        return float(ao.timing_args["rate"]) if ao is not None and ao.timing_args else 0.0

    def played_volts(self) -> np.ndarray:
        """Every AO sample the DAC put out, ``(n, 3)`` volts, in order, across tasks."""
        return np.vstack(self.played) if self.played else np.empty((0, 3))
