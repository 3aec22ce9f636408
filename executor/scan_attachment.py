"""The first full scan as a run-log attachment: what a resumed run registers its
relocalisation windows against (:mod:`.relocalise`).

The ``/scan`` channel shows the scan in Foxglove; the attachment keeps it exactly
(float64 heights, pixel size, origin in the layout frame) in NumPy's ``.npz`` format,
read back without pickles.
"""

from __future__ import annotations

import io
import zipfile

import numpy as np

from nanoasm.instrument import HeightImage

#: The attachment's name in a run log.
FULL_SCAN_ATTACHMENT = "full_scan.npz"


def full_scan_bytes(doc: dict) -> bytes:
    """A full-scan document (``height``, ``pixel_size``, ``origin``) as ``.npz`` bytes."""
    buf = io.BytesIO()
    np.savez_compressed(buf, height=np.asarray(doc["height"], float),
                        pixel_size=np.float64(doc["pixel_size"]), origin=np.asarray(doc["origin"], float))
    return buf.getvalue()


def full_scan_image(data: bytes) -> HeightImage:
    """The image :func:`full_scan_bytes` wrote; ValueError when the bytes are not one."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as f:
            height, px, origin = f["height"], float(f["pixel_size"]), f["origin"]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"not a full-scan attachment ({err})") from None
    if height.ndim != 2 or origin.shape != (2,) or not np.all(np.isfinite(height)):
        raise ValueError("not a full-scan attachment (bad shapes or values)")
    return HeightImage(height, px, (float(origin[0]), float(origin[1])), "run log")
