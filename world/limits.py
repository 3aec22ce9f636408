"""Limits of a height image: what :func:`~nanoasm.world.readers.read_height_image` reads
and :func:`~nanoasm.world.identify.identify` identifies.

A file or option beyond one of them is refused in one line naming the file (or the
option) and the limit, before anything large is allocated: a hostile or corrupt file
ends in bounded time and memory, never in an internal error.
"""

from __future__ import annotations

#: Largest image read, in pixels (4096 x 4096). Checked against the shape a file declares
#: (the ``.npy`` header, inside an ``.npz`` too; a JPK file's TIFF pages) before its data
#: are read, and against every image read. Identifying a 4096 x 4096 image takes about
#: 0.9 GB and 13 s here; AFM images are rarely beyond 4096 pixels a side.
MAX_PIXELS = 4096 * 4096
#: Smallest and largest pixel size, nm (0.01 nm to 1 mm): beyond them geometry
#: underflows or overflows (a pixel of 1e-300 nm collapses every outline to a point).
MIN_PIXEL_SIZE = 0.01
MAX_PIXEL_SIZE = 1e6
#: Largest height magnitude, nm (1 mm, far beyond any scanner's Z range): larger values
#: (1e308) overflow the levelling and shape fits. Usually a wrong unit.
MAX_HEIGHT = 1e6
#: An image is refused when more than this share of its pixels has no finite height
#: (NaN or infinity): too little is left to level, and objects split at the gaps.
MAX_INVALID_SHARE = 0.5
#: From this share of pixels without a finite height on, reading the image warns (one
#: line): objects over such pixels are missed or cut.
WARN_INVALID_SHARE = 0.01
#: Largest tip radius identification models, nm (100 µm, beyond colloidal probes): a
#: larger one overflows the tip image.
MAX_TIP_RADIUS = 1e5
