"""The instrument file: how a hardware backend reaches the microscope.

``format = "nanoasm.instrument/1"``, in TOML or JSON, with ``backend = "nidaq"`` (the
default: an NI DAQ card, :mod:`nanoasm.executor.nidaq`) or ``backend = "nanonis"`` (a
Nanonis controller over its TCP interface, :mod:`nanoasm.executor.nanonis`) and these
tables:

``[scanner]``
    The :class:`~nanoasm.instrument.InstrumentConfig` keys, read exactly as a
    scene's ``[scanner]`` table. On hardware the keys that decide what reaches the
    piezos are required (:data:`SCANNER_REQUIRED`): a default Bioscope calibration must
    never drive another scanner by omission. ``sample_rate`` is the DAQ's sample clock.
``[daq]``
    The NI device and its channels: ``device``; ``[daq.ao]`` ``x``, ``y``, ``z``
    (``"ao0"``...); ``[daq.ai]`` ``normal`` (S_n), ``lateral`` (S_l), ``height`` (the
    controller's topography signal), ``terminal``, ``signal_range``, ``height_range``;
    and the stream: ``chunk_size`` (samples per refill), ``lead_chunks`` (refills queued
    ahead of the DAC), ``buffer_size`` (samples per channel), ``timeout`` (s). Backend
    ``"nidaq"`` only.
``[nanonis]``
    The Nanonis controller, backend ``"nanonis"`` only: ``host``, ``port``, ``timeout``
    (s), the signal indexes ``normal`` (S_n) and ``lateral`` (S_l), ``scan_channel`` (the
    Z signal's scan slot), ``centre`` (Nanonis XY of the travel's centre, nm),
    ``setpoint``, ``leg``, ``lifted_leg`` and ``z_step`` (nm); see
    :mod:`nanoasm.executor.nanonis_config`.
``[imaging]``
    Scans under the controller's Z feedback: ``line_speed`` and ``full_scan_speed``
    (nm/s), ``settle`` (s held engaged before a scan) and ``height_nm_per_volt``
    (required for ``"nidaq"``; negative flips the sign of the height signal; not for
    ``"nanonis"``, whose heights are its Z signal in metres).
``[cantilever]``, ``[friction]``, ``[baseline]``, ``[calibration]``
    The lever the run compensates with, its tip-substrate friction, the detector's
    free-air baseline maps, and where ``nanoasm calibrate`` measures them
    (:mod:`nanoasm.executor.lever_file`); ``nanoasm run`` needs ``[cantilever]``.

No ``[scaling]`` table: AO volts are the scanner's DAC volts (``[scanner]
nm_per_volt`` already maps them to nm) and the height signal's scale is in
``[imaging]``. Every problem is one :class:`~nanoasm.errors.InputError` line naming the
file and the key path, e.g. ``lab.toml: daq.ai.hieght: unknown key (did you mean 'height'?)``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass

from nanoasm.errors import InputError
from nanoasm.fileio import read_document
from nanoasm.instrument import InstrumentConfig
from nanoasm.param import ParamError, param, validate
from nanoasm.schema import Table, check_format
from nanoasm.world.param_spec import from_table

from .calibration import CalibrationSites
from .lever_file import InstrumentLever, lever_from_tables, sites_from_table
from .nanonis_config import NanonisConfig, nanonis_from_table
from .strategy import ExecOptions

FORMAT = "nanoasm.instrument/1"

#: The lever's tables (:mod:`.lever_file`): optional in the file, ``[cantilever]`` needed by a run.
LEVER_TABLES = ("cantilever", "friction", "baseline", "calibration")

#: ``[scanner]`` keys an instrument file must state (the rest keep their defaults).
SCANNER_REQUIRED = ("xy_range", "z_range", "nm_per_volt", "dac_bits", "volt_range", "sample_rate",
                    "max_speed")

#: ``backend`` values: the hardware an instrument file drives.
BACKENDS = ("nidaq", "nanonis")

#: ``[daq.ai] terminal`` values and the ``nidaqmx.constants.TerminalConfiguration`` member of each.
TERMINALS = {"differential": "DIFF", "rse": "RSE", "nrse": "NRSE", "pseudodifferential": "PSEUDO_DIFF"}

#: Shortest refill interval (s): the every-N-samples callback runs in Python.
MIN_REFILL = 0.005

_DEVICE = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")
_AO, _AI = re.compile(r"ao[0-9]+"), re.compile(r"ai[0-9]+")


@dataclass(frozen=True)
class DaqConfig:
    """The NI-DAQmx device, its channels and the stream sizes: the ``[daq]`` table.

    Attributes
    ----------
    device : str
        NI device name as in NI MAX, e.g. ``"Dev1"``.
    ao : (x, y, z) of str
        Analog outputs driving the scanner, e.g. ``("ao0", "ao1", "ao2")``.
    ai : (normal, lateral, height) of str
        Analog inputs: S_n, S_l and the controller's height signal.
    terminal : str
        AI terminal configuration, a key of :data:`TERMINALS`.
    signal_range, height_range : (low, high) volts
        AI input ranges of the photodiode signals and of the height signal.
    chunk_size : int
        Samples per channel written at each refill (the every-N-samples event).
    lead_chunks : int
        Refills kept queued ahead of the DAC; latency ``lead_chunks * chunk_size / rate``.
    buffer_size : int
        AO and AI buffer, samples per channel; at least ``(lead_chunks + 1) * chunk_size``.
    timeout : float
        Seconds a DAQ read may wait beyond the stream's own latency.
    """

    device: str
    ao: tuple[str, str, str]
    ai: tuple[str, str, str]
    terminal: str = "differential"
    signal_range: tuple[float, float] = (-10.0, 10.0)
    height_range: tuple[float, float] = (-10.0, 10.0)
    chunk_size: int = 1000
    lead_chunks: int = 4
    buffer_size: int = 20000
    timeout: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.device, str) or not _DEVICE.fullmatch(self.device):
            raise ParamError("device", f"must be an NI device name such as 'Dev1', got {self.device!r}")
        for group, names, pattern, example in (("ao", ("x", "y", "z"), _AO, "ao0"),
                                               ("ai", ("normal", "lateral", "height"), _AI, "ai0")):
            _check_channels(group, getattr(self, group), names, pattern, example)
        if self.terminal not in TERMINALS:
            raise ParamError("ai.terminal", f"must be one of {', '.join(map(repr, TERMINALS))}, "
                             f"got {self.terminal!r}")
        for key in ("signal_range", "height_range"):
            lo, hi = getattr(self, key)
            if not lo < hi:
                raise ParamError(f"ai.{key}", f"low end must be below the high end, got [{lo:g}, {hi:g}]")
        for key, least in (("chunk_size", 1), ("lead_chunks", 2), ("buffer_size", 2)):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ParamError(key, f"must be an integer of at least {least}, got {value!r}")
        need = (self.lead_chunks + 1) * self.chunk_size
        if self.buffer_size < need:
            raise ParamError("buffer_size", f"must hold (lead_chunks + 1) x chunk_size = {need} samples, "
                             f"got {self.buffer_size}")
        if not self.timeout > 0:
            raise ParamError("timeout", f"must be positive, got {self.timeout!r}")

    def physical(self, channel: str) -> str:
        """``"Dev1/ao0"`` for ``"ao0"``."""
        return f"{self.device}/{channel}"

    @property
    def clock_terminal(self) -> str:
        """The AO sample clock terminal, the AI task's clock source: ``/Dev1/ao/SampleClock``."""
        return f"/{self.device}/ao/SampleClock"


def _check_channels(group: str, channels, names, pattern, example) -> None:
    if not isinstance(channels, tuple) or len(channels) != len(names):
        raise ParamError(group, f"must name {len(names)} channels ({', '.join(names)}), got {channels!r}")
    seen: dict[str, str] = {}
    for name, ch in zip(names, channels):
        if not isinstance(ch, str) or not pattern.fullmatch(ch):
            raise ParamError(f"{group}.{name}", f"must be a channel of the device such as {example!r} "
                             f"(without the device name), got {ch!r}")
        if ch in seen:
            raise ParamError(f"{group}.{name}", f"channel {ch!r} is already {group}.{seen[ch]}")
        seen[ch] = name


@dataclass(frozen=True)
class ImagingConfig:
    """Scans under the controller's Z feedback: the ``[imaging]`` table."""

    line_speed: float = param(2000.0, "nm/s", "tip speed along a local scan line",
                              source="seed 5: a 1 Hz, 1 µm line", positive=True)
    full_scan_speed: float = param(20000.0, "nm/s", "tip speed along a full-scan line (trace and "
                                   "retrace)", source="1 Hz over 10 µm", positive=True)
    settle: float = param(0.2, "s", "engaged hold before a scan starts, for the feedback to settle",
                          nonnegative=True, hi=60.0)
    height_nm_per_volt: float = param(250.0, "nm/V", "height per volt of the controller's height "
                                      "signal; negative if the signal falls as the surface rises",
                                      required=True)

    def __post_init__(self) -> None:
        validate(self)
        if self.height_nm_per_volt == 0:
            raise ParamError("height_nm_per_volt", "must not be zero")


@dataclass(frozen=True)
class InstrumentFile:
    """A loaded instrument file; build it with :func:`load_instrument_config`."""

    scanner: InstrumentConfig
    daq: DaqConfig | None       # backend "nidaq"
    imaging: ImagingConfig
    name: str = ""
    source: str = ""
    backend: str = "nidaq"
    nanonis: NanonisConfig | None = None    # backend "nanonis"
    lever: InstrumentLever | None = None    # [cantilever], [friction], [baseline] (lever_file)
    calibration: CalibrationSites | None = None     # [calibration]: where nanoasm calibrate measures

    def __post_init__(self) -> None:
        s = self.scanner
        for key in ("line_speed", "full_scan_speed"):
            if getattr(self.imaging, key) > s.max_speed:
                raise ParamError(f"imaging.{key}", f"must be at most scanner.max_speed ({s.max_speed:g} nm/s), "
                                 f"got {getattr(self.imaging, key):g}")
        if (self.daq is None) != (self.backend != "nidaq") or (self.nanonis is None) != (self.backend != "nanonis"):
            raise ParamError("backend", f"{self.backend!r} needs its own table ([daq] for 'nidaq', [nanonis] for "
                             "'nanonis') and no other")
        refill = self.daq.chunk_size / s.sample_rate if self.daq is not None else math.inf
        if refill < MIN_REFILL:
            least = math.ceil(MIN_REFILL * s.sample_rate)
            raise ParamError("daq.chunk_size", f"{self.daq.chunk_size} samples is {refill * 1e3:.3g} ms at "
                             f"{s.sample_rate:g} Hz; refills must be at least {MIN_REFILL * 1e3:g} ms apart "
                             f"(chunk_size >= {least})")

    @property
    def latency(self) -> float:
        """Seconds between handing a sample to the stream and the DAC playing it (at most)."""
        return (self.daq.lead_chunks + 1) * self.daq.chunk_size / self.scanner.sample_rate


def instrument_from_dict(data: dict, source: str | None = None) -> InstrumentFile:
    """Validate a parsed instrument document."""
    check_format(data, source, FORMAT)
    t = Table(data, source)
    if "timing" in t:       # a scene's table: refused outright, not as a likely typo of "imaging"
        t.fail("timing", "not an instrument file table: [timing] is the simulated instrument's, in a scene; "
                         f"a run scans at [imaging]'s speeds and pushes at {ExecOptions().push_speed:g} nm/s "
                         "(ExecOptions.push_speed)")
    t.check_keys(required=("format", "scanner", "imaging"), optional=("name", "backend", "daq", "nanonis",
                                                                     *LEVER_TABLES))
    name = t.string("name", "")
    backend = t.string("backend", "nidaq", choices=BACKENDS)
    st = t.table("scanner")
    st.check_keys(required=SCANNER_REQUIRED, optional=[f.name for f in dataclasses.fields(InstrumentConfig)])
    scanner = from_table(InstrumentConfig, st)
    daq, nanonis, imaging = _backend_tables(t, backend)
    lever, sites = lever_from_tables(t), sites_from_table(t, scanner)
    try:
        return InstrumentFile(scanner, daq, imaging, name, source or "", backend=backend, nanonis=nanonis,
                              lever=lever, calibration=sites)
    except ParamError as e:
        raise InputError(source, e.key, e.problem) from None


def _backend_tables(t: Table, backend: str) -> tuple[DaqConfig | None, NanonisConfig | None, ImagingConfig]:
    """``[daq]`` (NI) or ``[nanonis]``, the other refused, and ``[imaging]``."""
    own, other = ("daq", "nanonis") if backend == "nidaq" else ("nanonis", "daq")
    if other in t:
        t.fail(other, f"not a table of backend = {backend!r} (its hardware is in [{own}])")
    it = t.table("imaging")
    if backend == "nidaq":
        return _daq(t.table("daq")), None, from_table(ImagingConfig, it)
    if "height_nm_per_volt" in it:
        it.fail("height_nm_per_volt", "not used by backend 'nanonis': its heights are the Z signal in metres")
    imaging = from_table(ImagingConfig, Table({**it.data, "height_nm_per_volt": 1e9}, it.source, it.path))
    return None, nanonis_from_table(t.table("nanonis")), imaging


def _daq(t: Table) -> DaqConfig:
    t.check_keys(required=("device", "ao", "ai"),
                 optional=("chunk_size", "lead_chunks", "buffer_size", "timeout"))
    device = t.string("device")
    ao = t.table("ao")
    ao.check_keys(required=("x", "y", "z"))
    ai = t.table("ai")
    ai.check_keys(required=("normal", "lateral", "height"),
                  optional=("terminal", "signal_range", "height_range"))
    kwargs = {
        "device": device,
        "ao": tuple(ao.string(k) for k in ("x", "y", "z")),
        "ai": tuple(ai.string(k) for k in ("normal", "lateral", "height")),
        "terminal": ai.string("terminal", "differential", choices=TERMINALS),
        "signal_range": ai.pair("signal_range", (-10.0, 10.0), names=("low", "high")),
        "height_range": ai.pair("height_range", (-10.0, 10.0), names=("low", "high")),
        "chunk_size": t.integer("chunk_size", 1000, lo=1),
        "lead_chunks": t.integer("lead_chunks", 4, lo=2),
        "buffer_size": t.integer("buffer_size", 20000, lo=2),
        "timeout": t.number("timeout", 10.0, positive=True, hi=3600.0),
    }
    try:
        return DaqConfig(**kwargs)
    except ParamError as e:
        raise t.error(e.key, e.problem) from None


def load_instrument_config(path: str | os.PathLike) -> InstrumentFile:
    """Load and validate an instrument file (TOML or JSON).

    Raises
    ------
    InputError
        One line naming the file, the key path and the problem: an unknown key (with
        the nearest allowed one), a missing key, a wrong type, a non-finite number, a
        value out of range, an unknown or unsupported ``format``.
    """
    return instrument_from_dict(read_document(path), str(path))


__all__ = ["BACKENDS", "FORMAT", "SCANNER_REQUIRED", "TERMINALS", "DaqConfig", "ImagingConfig", "InstrumentFile",
           "instrument_from_dict", "load_instrument_config"]
