"""Reading AFM height images from instrument and text files; the simulator's scan file.

:func:`read_height_image` picks the reader from the file name:

============================  =====================================================
suffix                        format (reader)
============================  =====================================================
``.gwy``                      Gwyddion (gwyfile)
``.stp``                      WSxM (AFMReader)
``.jpk``, ``.jpk-qi-image``   JPK (AFMReader)
``.spm``                      Bruker Nanoscope (AFMReader, pySPM)
``.ibw``                      Igor / Asylum Research (AFMReader, igor2)
``.txt .asc .csv .dat``       ASCII matrix (:mod:`~nanoasm.world.readers_text`)
``.xyz``                      ASCII x y z on a regular grid
``.npy``                      NumPy array, nm, first row on top; needs ``pixel_size``
``.npz``                      nanoasm scan: ``height`` (nm, row 0 at the bottom),
                              ``pixel_size`` (nm), ``origin`` (nm, lower-left)
============================  =====================================================

Every image comes back in nm with row 0 at the bottom. Whatever goes wrong (unknown
suffix, missing pixel size, unreadable or corrupt file, no finite height, wrong shape)
is an :class:`~nanoasm.errors.InputError` with one line naming the file.
"""

from __future__ import annotations

import io
import math
import os
import warnings
import zipfile
from pathlib import Path

import numpy as np

from nanoasm.errors import InputError
from nanoasm.fileio import write_atomic
from nanoasm.instrument import HeightImage

from .readers_instrument import read_gwy, read_ibw, read_jpk, read_spm, read_stp, short_message
from .readers_text import parse_matrix, parse_xyz

#: The scan file format written by :func:`save_height_image`.
SCAN_FORMAT = "nanoasm.scan/1"
TEXT_SUFFIXES = (".txt", ".asc", ".csv", ".dat")
#: Largest text file read (bytes).
MAX_TEXT = 512 * 1024 * 1024


def _read_text(path: Path, src: str) -> str:
    size = path.stat().st_size
    if size > MAX_TEXT:
        raise InputError(src, None, f"file is too large ({size} bytes)")
    raw = path.read_bytes()
    if b"\x00" in raw:
        raise InputError(src, None, "binary file, expected numbers as text")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _read_npy(path: Path, src: str, pixel_size: float | None):
    if pixel_size is None:
        raise InputError(src, "pixel_size", "a .npy file has no pixel size: pass it (--pixel-size)")
    z = np.load(path, allow_pickle=False)
    if z.dtype.kind not in "fiu":
        raise InputError(src, None, f"array of {z.dtype} is not numeric")
    return np.flipud(np.asarray(z, dtype=float)), pixel_size, (0.0, 0.0), {"format": "npy"}


def _read_npz(path: Path, src: str):
    with np.load(path, allow_pickle=False) as data:
        missing = [k for k in ("height", "pixel_size", "origin") if k not in data.files]
        if missing:
            raise InputError(src, missing[0], "missing from the scan file")
        z = np.asarray(data["height"])
        ps = np.asarray(data["pixel_size"])
        origin = np.asarray(data["origin"])
    if z.dtype.kind not in "fiu":
        raise InputError(src, "height", f"array of {z.dtype} is not numeric")
    if ps.shape != () or ps.dtype.kind not in "fiu" or not (math.isfinite(float(ps)) and ps > 0):
        raise InputError(src, "pixel_size", "must be one positive number")
    if origin.shape != (2,) or origin.dtype.kind not in "fiu" or not np.all(np.isfinite(origin)):
        raise InputError(src, "origin", "must be two finite numbers")
    return (np.asarray(z, dtype=float), float(ps), (float(origin[0]), float(origin[1])),
            {"format": "npz"})


#: Leading bytes of binary formats, checked before a library sees the file.
MAGIC = {".gwy": (b"GWYP",), ".npy": (b"\x93NUMPY",), ".npz": (b"PK\x03\x04", b"PK\x05\x06"),
         ".jpk": (b"II*\x00", b"MM\x00*"), ".jpk-qi-image": (b"II*\x00", b"MM\x00*")}
FORMAT_NAMES = {".gwy": "Gwyddion .gwy", ".stp": "WSxM .stp", ".jpk": "JPK", ".jpk-qi-image": "JPK",
                ".spm": "Bruker .spm", ".ibw": "Igor .ibw", ".npy": "NumPy .npy",
                ".npz": "nanoasm .npz scan", ".xyz": "XYZ text"}


def _kind(name: str) -> str:
    for suffix in (".jpk-qi-image", *FORMAT_NAMES, *TEXT_SUFFIXES):
        if name.endswith(suffix):
            return suffix
    return ""


def _check_magic(path: Path, src: str, kind: str) -> None:
    if kind not in MAGIC:
        return
    with open(path, "rb") as fh:
        head = fh.read(8)
    if not head.startswith(MAGIC[kind]):
        raise InputError(src, None, f"not a {FORMAT_NAMES[kind]} file (wrong leading bytes)")


def _load(path: Path, src: str, name: str, pixel_size: float | None, channel: str | None):
    if name.endswith(".gwy"):
        return read_gwy(path, src, channel)
    if name.endswith(".stp"):
        return read_stp(path, src, channel)
    if name.endswith((".jpk", ".jpk-qi-image")):
        return read_jpk(path, src, channel)
    if name.endswith(".spm"):
        return read_spm(path, src, channel)
    if name.endswith(".ibw"):
        return read_ibw(path, src, channel)
    if name.endswith(".npy"):
        return _read_npy(path, src, pixel_size)
    if name.endswith(".npz"):
        return _read_npz(path, src)
    if name.endswith(".xyz"):
        z, ps, origin = parse_xyz(_read_text(path, src), src, pixel_size)
        return z, ps, origin, {"format": "xyz"}
    if name.endswith(TEXT_SUFFIXES):
        z, ps = parse_matrix(_read_text(path, src), src, pixel_size)
        return z, ps, (0.0, 0.0), {"format": "ascii"}
    known = ".gwy .stp .jpk .jpk-qi-image .spm .ibw .xyz .npy .npz " + " ".join(TEXT_SUFFIXES)
    raise InputError(src, None,
                     f"unknown file type {path.suffix or '(no suffix)'!r}; expected one of {known}")


def read_height_image(path: str | os.PathLike, *, pixel_size: float | None = None,
                      channel: str | None = None) -> HeightImage:
    """Read a height image (nm, row 0 at the bottom) from any supported file.

    Parameters
    ----------
    path : path-like
    pixel_size : float, optional
        Pixel pitch in nm; overrides the file's own, required for ``.npy`` and for
        ASCII matrices without a size header.
    channel : str, optional
        Channel name (or Gwyddion channel number); a height channel by default.

    Raises
    ------
    InputError
        One line naming the file and the problem.
    """
    src = str(path)
    if pixel_size is not None and not (isinstance(pixel_size, (int, float))
                                       and math.isfinite(pixel_size) and pixel_size > 0):
        raise InputError(src, "pixel_size", f"must be a positive number, got {pixel_size!r}")
    p = Path(path)
    if not p.exists():
        raise InputError(src, None, "no such file")
    if p.is_dir():
        raise InputError(src, None, "is a directory, not a file")
    if p.stat().st_size == 0:
        raise InputError(src, None, "file is empty")
    kind = _kind(p.name.lower())
    what = FORMAT_NAMES.get(kind, "text")
    try:
        _check_magic(p, src, kind)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            z, ps, origin, meta = _load(p, src, p.name.lower(), pixel_size, channel)
    except InputError:
        raise
    except (OSError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(src, None, f"cannot read as {what}: {short_message(exc)}") from None
    except Exception as exc:                     # third-party readers raise anything on bad files
        raise InputError(src, None, f"corrupt or unreadable {what} file ({short_message(exc)})") from None
    return _checked(z, pixel_size or ps, origin, src, meta)


def _checked(z: np.ndarray, ps: float, origin, src: str, meta: dict) -> HeightImage:
    if z.ndim != 2 or min(z.shape) < 2:
        raise InputError(src, None, f"expected a 2-D image of at least 2 x 2 pixels, got shape {z.shape}")
    if not np.isfinite(z).any():
        raise InputError(src, None, "the image has no finite height")
    if not (math.isfinite(ps) and ps > 0):
        raise InputError(src, "pixel_size", f"must be positive, got {ps!r}")
    return HeightImage(np.ascontiguousarray(z, dtype=float), float(ps),
                       (float(origin[0]), float(origin[1])), src, meta)


def save_height_image(image: HeightImage, path: str | os.PathLike) -> None:
    """Write ``image`` as a nanoasm scan (``.npz``), atomically.

    Arrays: ``height`` (ny, nx) nm with row 0 at the bottom, ``pixel_size`` (nm),
    ``origin`` (2,) nm, ``format`` = ``"nanoasm.scan/1"``.
    """
    if not str(path).lower().endswith(".npz"):
        raise InputError(str(path), None, "a scan file must end in .npz")
    buf = io.BytesIO()
    np.savez_compressed(buf, height=np.asarray(image.height, dtype=float),
                        pixel_size=np.float64(image.pixel_size),
                        origin=np.asarray(image.origin, dtype=float),
                        format=np.str_(SCAN_FORMAT))
    write_atomic(path, buf.getvalue())
