"""Instrument file formats: Gwyddion (gwyfile), WSxM, JPK, Bruker and Igor (AFMReader).

Each ``read_*(path, src, channel)`` returns ``(height, pixel_size, origin, meta)`` with
heights in nm and row 0 at the *bottom* (the libraries give the top row first); a
problem the user can act on (no such channel, wrong unit) is an
:class:`~nanoasm.errors.InputError`, anything else propagates to
:func:`~nanoasm.world.readers.read_height_image`, which turns it into one line.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from nanoasm.errors import InputError

from .limits import MAX_PIXELS

#: Channels tried, in order, when none is given.
DEFAULT_CHANNELS = {
    "spm": ("Height", "Height Sensor", "ZSensor"),
    "ibw": ("HeightTracee", "HeightTrace", "Height"),
    "jpk": ("measuredHeight_trace", "height_trace"),
}


#: The standard-library loggers of the readers' libraries, silenced while they read: their
#: complaints about a bad file ("invalid offset to first page") would print before the one
#: line that says what is wrong.
LIBRARY_LOGGERS = ("tifffile", "igor2", "pySPM", "gwyfile", "AFMReader")


@contextmanager
def quiet_libraries() -> Iterator[None]:
    """Silence :data:`LIBRARY_LOGGERS` (and their children that log through them) for the
    duration; their levels are put back after."""
    saved = {}
    for name in LIBRARY_LOGGERS:
        logger = logging.getLogger(name)
        saved[name] = logger.level
        logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def short_message(exc: BaseException) -> str:
    """An exception's text on one line, at most 160 characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def _afmreader(module: str):
    """Import an AFMReader module with its logging silenced."""
    import importlib

    mod = importlib.import_module(f"AFMReader.{module}")
    from loguru import logger

    logger.disable("AFMReader")
    return mod


def _with_channels(load, path: Path, src: str, kind: str, channel: str | None):
    names = (channel,) if channel else DEFAULT_CHANNELS[kind]
    last: Exception | None = None
    for name in names:
        try:
            image, px = load(path, name)
            return np.asarray(image, dtype=float), float(px), name
        except (ValueError, KeyError) as exc:
            last = exc
            if "channel" not in str(exc).lower():
                raise
    raise InputError(src, "channel", short_message(last) if last else "no height channel")


def read_stp(path: Path, src: str, channel: str | None):
    z, px = _afmreader("stp").load_stp(path)
    return np.flipud(np.asarray(z, dtype=float)), float(px), (0.0, 0.0), {"format": "stp"}


def _check_tiff(path: Path, src: str) -> None:
    """A JPK file is a TIFF: refuse one with no page, or a page beyond the pixel budget,
    before AFMReader decodes anything (a compressed page could be a bomb)."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        if not len(tif.pages):
            raise InputError(src, None, "not a JPK file (no image in the TIFF)")
        for i, page in enumerate(tif.pages):
            n = math.prod(getattr(page, "shape", ()) or (0,))
            if n > MAX_PIXELS:
                raise InputError(src, None, f"TIFF page {i} declares {n} pixels; at most {MAX_PIXELS} "
                                            "(MAX_PIXELS, 4096 x 4096) are read")


def read_jpk(path: Path, src: str, channel: str | None):
    _check_tiff(path, src)
    jpk = _afmreader("jpk")
    z, px, name = _with_channels(lambda p, c: jpk.load_jpk(p, c), path, src, "jpk", channel)
    return np.flipud(z), px, (0.0, 0.0), {"format": "jpk", "channel": name}


#: The line that ends a Bruker header: pySPM reads lines until one is exactly this (after
#: dropping backslashes and trailing white space), and loops forever without it.
SPM_HEADER_END = b"*File list end"
#: How far into a Bruker file its header end is looked for (bytes).
SPM_HEADER_MAX = 4 * 1024 * 1024


def _has_header_end(path: Path) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(SPM_HEADER_MAX + 1)
    lines = head.split(b"\n")
    if len(head) > SPM_HEADER_MAX:
        lines = lines[:-1]              # the last line may go on beyond what was read
    return any(line.rstrip().replace(b"\\", b"") == SPM_HEADER_END for line in lines)


def read_spm(path: Path, src: str, channel: str | None):
    if not _has_header_end(path):
        raise InputError(src, None, "not a Bruker .spm file (no header end marker)")
    spm = _afmreader("spm")
    z, px, name = _with_channels(lambda p, c: spm.load_spm(p, c), path, src, "spm", channel)
    return np.flipud(z), px, (0.0, 0.0), {"format": "spm", "channel": name}


def read_ibw(path: Path, src: str, channel: str | None):
    ibw = _afmreader("ibw")
    z, px, name = _with_channels(lambda p, c: ibw.load_ibw(p, c), path, src, "ibw", channel)
    return np.flipud(z), px, (0.0, 0.0), {"format": "ibw", "channel": name}


def read_gwy(path: Path, src: str, channel: str | None):
    import gwyfile

    obj = gwyfile.load(str(path))
    keys = sorted((k for k in obj if k.endswith("/data") and k.count("/") == 2),
                  key=lambda k: int(k.split("/")[1]) if k.split("/")[1].isdigit() else 1 << 30)
    if not keys:
        raise InputError(src, None, "no data channel in the Gwyddion file")
    titles = {k: str(obj.get(k + "/title", "")) for k in keys}
    if channel is not None:
        pick = [k for k in keys if titles[k] == channel or k.split("/")[1] == channel]
        if not pick:
            names = ", ".join(f"{k.split('/')[1]} ({titles[k]})" for k in keys)
            raise InputError(src, "channel", f"no channel {channel!r}; the file has {names}")
        key = pick[0]
    else:
        heights = [k for k in keys if _unit_str(obj[k].get("si_unit_z")) == "m"]
        if not heights:
            raise InputError(src, "channel", "no channel with heights in metres")
        named = [k for k in heights if any(w in titles[k].lower() for w in ("topo", "height", "z"))]
        key = (named or heights)[0]
    field = obj[key]
    xres, yres = int(field["xres"]), int(field["yres"])
    data = np.asarray(field["data"], dtype=float)
    if data.size != xres * yres:
        raise InputError(src, None, f"channel {key}: {data.size} values for {xres} x {yres} pixels")
    scale_xy = _scale(src, field.get("si_unit_xy"))
    scale_z = _scale(src, field.get("si_unit_z"))
    px, py = field["xreal"] * scale_xy / xres, field["yreal"] * scale_xy / yres
    if not math.isclose(px, py, rel_tol=1e-3):
        raise InputError(src, None, f"non-square pixels ({px:g} x {py:g} nm) are not supported")
    z = np.flipud(data.reshape(yres, xres) * scale_z)
    return z, float(px), (0.0, 0.0), {"format": "gwy", "channel": titles[key] or key}


def _unit_str(unit) -> str:
    if unit is None:
        return ""
    try:
        return str(unit["unitstr"]) if "unitstr" in unit else ""
    except TypeError:
        return ""


def _scale(src: str, unit) -> float:
    u = _unit_str(unit)
    table = {"m": 1e9, "": 1e9, "um": 1e3, "µm": 1e3, "nm": 1.0}
    if u not in table:
        raise InputError(src, None, f"channel unit {u!r} is not a length")
    return table[u]
