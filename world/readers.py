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
suffix, missing pixel size, unreadable or corrupt file, no finite height, wrong shape, a
limit of :mod:`~nanoasm.world.limits` passed) is an :class:`~nanoasm.errors.InputError`
with one line naming the file. A ``.npy`` array's declared shape (inside an ``.npz`` too)
is checked against the pixel budget before its data are read; the libraries' own logging
and warnings are silenced while they read.
"""

from __future__ import annotations

import io
import math
import os
import warnings
import zipfile
from pathlib import Path
from typing import IO

import numpy as np

from nanoasm.errors import InputError
from nanoasm.fileio import write_atomic
from nanoasm.instrument import HeightImage

from .limits import (MAX_HEIGHT, MAX_INVALID_SHARE, MAX_PIXEL_SIZE, MAX_PIXELS, MIN_PIXEL_SIZE, WARN_IMAGE_SIDE,
                     WARN_INVALID_SHARE)
from .readers_instrument import quiet_libraries, read_gwy, read_ibw, read_jpk, read_spm, read_stp, short_message
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


def _npy_header(fh: IO[bytes], src: str, key: str | None) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype an ``.npy`` stream declares, from its header alone."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = fmt.read_array_header_2_0(fh)
        else:
            raise InputError(src, key, f".npy format version {version[0]}.{version[1]} is not read "
                                       "(numeric arrays are written as 1.0)")
    except (ValueError, EOFError) as exc:
        raise InputError(src, key, f"not a NumPy array ({short_message(exc)})") from None
    return tuple(shape), dtype


def _checked_header(shape: tuple[int, ...], dtype: np.dtype, src: str, key: str | None,
                    limit: int = MAX_PIXELS) -> None:
    """Refuse, before reading its data, an array that is not numeric or declares more
    than ``limit`` values (a zip bomb's 6 GB height array is a few bytes of header)."""
    if dtype.kind not in "fiu":
        raise InputError(src, key, f"array of {dtype} is not numeric")
    n = math.prod(shape)
    if n > limit:
        most = f"{limit} (MAX_PIXELS, 4096 x 4096) are read" if limit == MAX_PIXELS else f"{limit} expected"
        raise InputError(src, key, f"declares shape ({', '.join(map(str, shape))}), {n} values; at most {most}")


def _read_npy(path: Path, src: str, pixel_size: float | None):
    if pixel_size is None:
        raise InputError(src, "pixel_size", "a .npy file has no pixel size: pass it (--pixel-size)")
    with open(path, "rb") as fh:
        _checked_header(*_npy_header(fh, src, None), src, None)
        fh.seek(0)
        z = np.lib.format.read_array(fh, allow_pickle=False)
    return np.flipud(np.asarray(z, dtype=float)), pixel_size, (0.0, 0.0), {"format": "npy"}


#: The arrays of a scan file and the most values each may declare.
_NPZ_ARRAYS = {"height": MAX_PIXELS, "pixel_size": 1, "origin": 2}


def _read_npz(path: Path, src: str):
    arrays = {}
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
        for key, limit in _NPZ_ARRAYS.items():
            member = next((m for m in (key + ".npy", key) if m in names), None)
            if member is None:
                raise InputError(src, key, "missing from the scan file")
            with zf.open(member) as fh:
                _checked_header(*_npy_header(fh, src, key), src, key, limit)
            with zf.open(member) as fh:
                arrays[key] = np.lib.format.read_array(fh, allow_pickle=False)
    z, ps, origin = arrays["height"], arrays["pixel_size"], arrays["origin"]
    if ps.shape != () or not (math.isfinite(float(ps)) and ps > 0):
        raise InputError(src, "pixel_size", "must be one positive number")
    if origin.shape != (2,) or not np.all(np.isfinite(origin)):
        raise InputError(src, "origin", "must be two finite numbers")
    return (np.asarray(z, dtype=float), float(ps), (float(origin[0]), float(origin[1])),
            {"format": "npz"})


#: Leading bytes of binary formats, checked before a library sees the file.
MAGIC = {".gwy": (b"GWYP",), ".npy": (b"\x93NUMPY",), ".npz": (b"PK\x03\x04", b"PK\x05\x06"),
         ".jpk": (b"II*\x00", b"MM\x00*"), ".jpk-qi-image": (b"II*\x00", b"MM\x00*"),
         # an Igor binary wave starts with its version, 1, 2, 3 or 5, as a 16-bit integer
         ".ibw": tuple(bytes(b) for v in (1, 2, 3, 5) for b in ((v, 0), (0, v)))}
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
        name = FORMAT_NAMES[kind]
        raise InputError(src, None, f"not {'an' if name[0] in 'AEIOU' else 'a'} {name} file (wrong leading bytes)")


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
    if pixel_size is not None:
        check_pixel_size(pixel_size, src, "pixel_size")
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
        with warnings.catch_warnings(), quiet_libraries():
            warnings.simplefilter("ignore")
            z, ps, origin, meta = _load(p, src, p.name.lower(), pixel_size, channel)
    except InputError:
        raise
    except (OSError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(src, None, f"cannot read as {what}: {short_message(exc)}") from None
    except Exception as exc:                     # third-party readers raise anything on bad files
        if isinstance(exc, NameError) and exc.__context__ is not None:
            exc = exc.__context__                # a reader's own handler failed: say what it was handling
        raise InputError(src, None, f"corrupt or unreadable {what} file ({short_message(exc)})") from None
    return _checked(z, pixel_size or ps, origin, src, meta)


def check_pixel_size(value, src: str | None, key: str) -> float:
    """``value`` as a pixel size (nm) within ``MIN_PIXEL_SIZE`` to ``MAX_PIXEL_SIZE``; else
    InputError naming ``src`` and ``key``."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not (ok and math.isfinite(value) and MIN_PIXEL_SIZE <= value <= MAX_PIXEL_SIZE):
        what = "a positive number" if not (ok and value > 0) else "a pixel size"
        raise InputError(src, key, f"must be {what} from {MIN_PIXEL_SIZE:g} to {MAX_PIXEL_SIZE:g} nm, "
                                   f"got {value!r}")
    return float(value)


def _checked(z: np.ndarray, ps: float, origin, src: str, meta: dict) -> HeightImage:
    if z.ndim != 2 or min(z.shape) < 2:
        raise InputError(src, None, f"expected a 2-D image of at least 2 x 2 pixels, got shape {z.shape}")
    if z.size > MAX_PIXELS:
        raise InputError(src, None, f"{z.shape[0]} x {z.shape[1]} pixels; at most {MAX_PIXELS} "
                                    "(MAX_PIXELS, 4096 x 4096) are read")
    finite = np.isfinite(z)
    valid = int(np.count_nonzero(finite))
    if not valid:
        raise InputError(src, None, "the image has no finite height")
    invalid = 1.0 - valid / z.size
    if invalid > MAX_INVALID_SHARE:     # the counts too: 50.01 % shows as "50%", the limit
        raise InputError(src, None, f"{z.size - valid} of {z.size} pixels ({invalid:.0%}) have no finite "
                                    f"height (NaN or infinity); at most {MAX_INVALID_SHARE:.0%} "
                                    f"({math.floor(MAX_INVALID_SHARE * z.size)}) may")
    top = float(np.max(np.abs(z[finite])))
    if top > MAX_HEIGHT:
        raise InputError(src, None, f"heights reach {top:.3g} nm; at most {MAX_HEIGHT:g} nm (1 mm) is read "
                                    "(a wrong unit?)")
    check_pixel_size(ps, src, "pixel_size")
    return HeightImage(np.ascontiguousarray(z, dtype=float), float(ps),
                       (float(origin[0]), float(origin[1])), src, meta)


def image_warnings(image: HeightImage) -> list[str]:
    """What a user should know about an image read (one line each, naming its source):
    pixels without a finite height from ``WARN_INVALID_SHARE`` of the image on, and an
    extent beyond ``WARN_IMAGE_SIDE`` (1 mm, more than any AFM scanner's range: its
    units are likely wrong)."""
    n = image.height.size
    out = []
    invalid = n - int(np.count_nonzero(np.isfinite(image.height)))
    if invalid and invalid / n >= WARN_INVALID_SHARE:
        out.append(f"{image.source or 'image'}: {invalid} of {n} pixels ({invalid / n:.0%}) have no finite "
                   "height (NaN or infinity); objects over them are missed or cut")
    ny, nx = image.height.shape
    w, h = nx * image.pixel_size, ny * image.pixel_size
    if max(w, h) > WARN_IMAGE_SIDE:
        out.append(f"{image.source or 'image'}: the image spans {w:g} x {h:g} nm, more than 1 mm: are its "
                   f"units right (pixel size {image.pixel_size:g} nm; --pixel-size sets it)?")
    return out


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
