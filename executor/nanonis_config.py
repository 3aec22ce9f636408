"""The ``[nanonis]`` table of an instrument file: where the Nanonis controller listens and
which of its signals the backend reads (:mod:`nanoasm.executor.nanonis`).

Keys (nm, s as everywhere; indexes as the Nanonis software numbers them):

``host``, ``port`` (required)
    The TCP Programming Interface of the Nanonis software (File > Settings > TCP
    Programming Interface; its ports are 6501-6504 by default).
``timeout`` (s, default 10)
    How long connecting, and each reply, may take beyond the command's own duration
    (a follow-me move's length over its speed, a frame's lines over the scan speed).
``normal``, ``lateral`` (required)
    Signal indexes (0-127, ``Signals.ValsGet``) of the photodiode's S_n and S_l.
``scan_channel`` (required)
    The Z (m) signal's slot (0-23) among the signals the Signals Manager assigns to
    scans: the channel a full scan records and grabs.
``centre`` ([x, y] nm, default [0, 0])
    The Nanonis XY coordinates of the centre of the scanner's travel (``[scanner]
    xy_range``): scanner-frame ``(xy_range / 2)`` is Nanonis ``centre``.
``setpoint`` (optional)
    Z-controller setpoint sent when the backend starts, in the unit of the controlled
    signal; without it the controller keeps the one it has.
``leg`` (nm, default 50), ``lifted_leg`` (nm, default 1000)
    Longest straight move between two signal reads while a tip path streams, where it
    reaches the surface (z <= 0) and where it stays lifted: the signals' resolution
    along a push, a force curve (``leg``) or a baseline map (``lifted_leg``).
``z_step`` (nm, default 20)
    Largest Z step of one ``ZCtrl.ZPosSet`` while Z moves with the controller off.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from nanoasm.instrument.protocol import MAX_SCANNER_RANGE
from nanoasm.param import ParamError
from nanoasm.schema import Table

#: Largest signal index of ``Signals.ValsGet`` and largest scan-buffer slot.
MAX_SIGNAL, MAX_SLOT = 127, 23

_HOST = re.compile(r"[A-Za-z0-9_.:\[\]-]+")
_KEYS = ("host", "port", "timeout", "normal", "lateral", "scan_channel", "centre", "setpoint", "leg", "lifted_leg",
         "z_step")


@dataclass(frozen=True)
class NanonisConfig:
    """The Nanonis controller and its signals: the ``[nanonis]`` table (see the module)."""

    host: str
    port: int
    normal: int
    lateral: int
    scan_channel: int
    timeout: float = 10.0
    centre: tuple[float, float] = (0.0, 0.0)
    setpoint: float | None = None
    leg: float = 50.0
    lifted_leg: float = 1000.0
    z_step: float = 20.0

    def __post_init__(self) -> None:
        if not isinstance(self.host, str) or not _HOST.fullmatch(self.host):
            raise ParamError("host", f"must be a host name or IP address such as 'localhost', got {self.host!r}")
        for key, lo, hi in (("port", 1, 65535), ("normal", 0, MAX_SIGNAL), ("lateral", 0, MAX_SIGNAL),
                            ("scan_channel", 0, MAX_SLOT)):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise ParamError(key, f"must be an integer from {lo} to {hi}, got {value!r}")
        if self.normal == self.lateral:
            raise ParamError("lateral", f"signal {self.lateral} is already normal")
        for key, hi in (("timeout", 3600.0), ("leg", 1e4), ("lifted_leg", 1e6), ("z_step", 1e4)):
            value = getattr(self, key)
            if not 0 < value <= hi:
                raise ParamError(key, f"must be positive and at most {hi:g}, got {value!r}")
        if any(abs(c) > MAX_SCANNER_RANGE for c in self.centre):
            raise ParamError("centre", f"must lie within ±{MAX_SCANNER_RANGE:g} nm, got {self.centre!r}")

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"


def nanonis_from_table(t: Table) -> NanonisConfig:
    """Read and check the ``[nanonis]`` table; errors are one line naming the key."""
    t.check_keys(required=("host", "port", "normal", "lateral", "scan_channel"), optional=_KEYS)
    kwargs = {
        "host": t.string("host"),
        "port": t.integer("port", lo=1, hi=65535),
        "normal": t.integer("normal", lo=0, hi=MAX_SIGNAL),
        "lateral": t.integer("lateral", lo=0, hi=MAX_SIGNAL),
        "scan_channel": t.integer("scan_channel", lo=0, hi=MAX_SLOT),
        "timeout": t.number("timeout", 10.0, positive=True, hi=3600.0),
        "centre": t.pair("centre", (0.0, 0.0), lo=-MAX_SCANNER_RANGE, hi=MAX_SCANNER_RANGE),
        "setpoint": t.number("setpoint", None),
        "leg": t.number("leg", 50.0, positive=True, hi=1e4),
        "lifted_leg": t.number("lifted_leg", 1000.0, positive=True, hi=1e6),
        "z_step": t.number("z_step", 20.0, positive=True, hi=1e4),
    }
    try:
        return NanonisConfig(**kwargs)
    except ParamError as e:
        raise t.error(e.key, e.problem) from None


__all__ = ["MAX_SIGNAL", "MAX_SLOT", "NanonisConfig", "nanonis_from_table"]
