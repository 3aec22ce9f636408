"""The first full scan as a run-log attachment: what a resumed run registers its
relocalisation windows against (:mod:`.relocalise`).

The ``/scan`` channel shows the scan in Foxglove; the attachment keeps it exactly
(float64 heights, pixel size, origin in the layout frame) in NumPy's ``.npz`` format,
read back without pickles.
"""

from __future__ import annotations

import io
import math
import zipfile
import zlib

import numpy as np

from nanoasm.instrument import HeightImage
from nanoasm.world.limits import MAX_PIXELS

#: The attachment's name in a run log.
FULL_SCAN_ATTACHMENT = "full_scan.npz"


#: Bytes of the heights deflated to tell whether deflating them all pays, and the share of
#: them it must save: a scan's float64 heights carry noise down to the last bits, and
#: deflating a 4000 x 4000 scan took 3.9 s to save 4 % of its 128 MB.
SAMPLE_BYTES, WORTH_SAVING = 1 << 20, 0.1


def full_scan_bytes(doc: dict) -> bytes:
    """A full-scan document (``height``, ``pixel_size``, ``origin``) as ``.npz`` bytes,
    deflated where a sample of the heights shows that it pays (:data:`WORTH_SAVING`)."""
    height = np.ascontiguousarray(doc["height"], float)
    sample = height.reshape(-1)[:SAMPLE_BYTES // 8].tobytes()
    save = np.savez_compressed if len(zlib.compress(sample, 1)) < (1.0 - WORTH_SAVING) * len(sample) else np.savez
    buf = io.BytesIO()
    save(buf, height=height, pixel_size=np.float64(doc["pixel_size"]), origin=np.asarray(doc["origin"], float))
    return buf.getvalue()


#: The most values each array of the attachment may declare (checked in its header first).
_SIZES = {"height": MAX_PIXELS, "pixel_size": 1, "origin": 2}


def _declared_sizes_ok(data: bytes) -> None:
    """Refuse, before any array is read, an attachment whose arrays declare more values
    than a full scan has (a zip bomb's header is a few bytes)."""
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for key, most in _SIZES.items():
            with zf.open(key + ".npy") as fh:
                version = np.lib.format.read_magic(fh)
                read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                        else np.lib.format.read_array_header_2_0)
                shape = read(fh)[0]
            if math.prod(shape) > most:
                raise ValueError(f"{key} declares {math.prod(shape)} values; at most {most}")


def full_scan_image(data: bytes) -> HeightImage:
    """The image :func:`full_scan_bytes` wrote; ValueError when the bytes are not one."""
    try:
        _declared_sizes_ok(data)
        with np.load(io.BytesIO(data), allow_pickle=False) as f:
            height, px, origin = f["height"], float(f["pixel_size"]), f["origin"]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"not a full-scan attachment ({err})") from None
    if height.ndim != 2 or origin.shape != (2,) or not np.all(np.isfinite(height)):
        raise ValueError("not a full-scan attachment (bad shapes or values)")
    return HeightImage(height, px, (float(origin[0]), float(origin[1])), "run log")
