"""Limits of what nanoasm reads: a height image (what
:func:`~nanoasm.world.readers.read_height_image` reads and
:func:`~nanoasm.world.identify.identify` identifies), and the plausible ranges of a
scene's drift, noise and push speed and of a layout's working area.

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
#: An image wider or taller than this (nm: 1 mm, more than any AFM scanner's range) is
#: read with a one-line warning: its units are likely wrong.
WARN_IMAGE_SIDE = 1e6
#: Largest tip radius identification models, nm (100 µm, beyond colloidal probes): a
#: larger one overflows the tip image.
MAX_TIP_RADIUS = 1e5

# -- scenes, layouts and environments ----------------------------------------------------
# ``nanoasm scene check`` and ``layout check`` refuse what a run could not work with, as
# the run itself would: a value beyond one of these is one line naming the file, the key
# and the limit, never a crash or a silent "0 of N filled" later.

#: Fastest steady drift a scene may give, nm/s (each component of ``[drift] velocity``):
#: 36 µm an hour. A settled AFM drifts 0.01-1 nm/s (the seed: several hundred nm an hour);
#: from about 3 nm/s on, the rows of a 5-minute full scan smear every object beyond
#: recognition, and faster still the sample leaves the scan. Beyond it, usually a wrong unit.
MAX_DRIFT_SPEED = 10.0
#: Largest random walk of the drift, nm/√s (``[drift] random_walk``; the default 0.1 wanders
#: 6 nm in an hour, this 600 nm).
MAX_DRIFT_RANDOM_WALK = 10.0
#: Largest steady change of the drift velocity, nm/s² (``[drift_change] acceleration``,
#: each component): MAX_DRIFT_SPEED gained in 17 minutes. Thermal settling is some
#: 1e-4 nm/s² (the scene families draw up to 8e-5).
MAX_DRIFT_ACCELERATION = 0.01
#: Largest sudden drift jump, nm (``[drift_change] jump``): 10 µm, a knock that moves the
#: sample by a good part of the working area.
MAX_DRIFT_JUMP = 10_000.0
#: Largest height noise, nm RMS per sample (``[noise] height_rms``). An AFM's noise floor
#: is 0.05-1 nm; at 10 nm, objects of tens of nm are hardly told from the substrate.
MAX_HEIGHT_NOISE = 10.0
#: Slowest push, nm/s (``[timing] push_speed`` of a scene, which a dry-run pushes at, and
#: ``ExecOptions.push_speed``): a 1 µm push then takes 17 minutes. Slower pushes take
#: years of instrument time and as many DAC samples.
MIN_PUSH_SPEED = 1.0
#: Largest side of a layout's working area, nm (40.96 µm). A run scans the whole working
#: area first, at 10 nm per pixel (``ExecOptions.pixel_size``), and an image has at most
#: MAX_PIXELS (4096 a side); it must also fit the scanner's XY range (90 µm by default),
#: which ``dry-run`` and ``run`` check against the scene's or the instrument file's.
MAX_LAYOUT_SIDE = 40_960.0

# -- a scene's instrument and sample at extremes ------------------------------------------
# Beyond these the simulated instrument overflows, allocates without bound or loops for
# ever (a tip of 1e-300 nm, a lever gain of 1e308, a line of 1e308 s, jumps every 1e-9 s);
# each is far outside any real AFM. ``scene check`` refuses a value beyond one, naming the
# key (world/params.py declares them on the keys).

#: Tip apex radius of a scene, nm (``[tip] radius``): 1 nm (the sharpest tips) to 1 µm
#: (a blunt tip pushes nothing of tens of nm; colloidal probes do not push).
MIN_TIP_RADIUS = 1.0
MAX_SCENE_TIP_RADIUS = 1000.0
#: Normal signal gain of the lever, nm/V (``[cantilever] K_n``; the seed's 89).
MIN_LEVER_GAIN = 1.0
MAX_LEVER_GAIN = 10_000.0
#: Lever length, nm (``[cantilever] length``): 10 µm to 1 mm.
MIN_LEVER_LENGTH = 10_000.0
MAX_LEVER_LENGTH = 1e6
#: (The scanner's slew limit, ``[scanner] max_speed``, is bounded by MIN_SCANNER_SPEED and
#: MAX_SCANNER_SPEED of :mod:`nanoasm.instrument.protocol`, as its range and sample rate.)
#: Time of one full-scan line, s (``[timing] full_scan_line``): 10 ms to 100 s.
MIN_SCAN_LINE_TIME = 0.01
MAX_SCAN_LINE_TIME = 100.0
#: Time of one local-scan sample, s (``[timing] scan_line_sample``; the default 1 ms):
#: 10 µs to 0.1 s. At 1 s a sample, each reference scan outlasts the drift it measures
#: and a dry-run of one slot had not ended after 5 minutes.
MIN_SAMPLE_TIME = 1e-5
MAX_SAMPLE_TIME = 0.1
#: Longest pause of the instrument, s (``[timing] scan_line_overhead``, ``mode_switch``;
#: ``[drift_change] jump_duration``): 10 minutes.
MAX_PAUSE = 600.0
#: Shortest period of repeated drift jumps, s (``[drift_change] jump_every``, unless 0):
#: two knocks a second are vibration, not drift (every jump of a run is drawn and summed).
MIN_JUMP_EVERY = 0.5
#: Most repeated jumps under way at once: ``jump_duration`` is at most this many
#: ``jump_every`` (each sample of the drift sums the steps under way).
MAX_OVERLAPPING_JUMPS = 10
#: Largest gap at which the van der Waals error acts, nm (``[vdw] range``), and its
#: largest amplitude (``[vdw] amplitude``).
MAX_VDW_RANGE = 1000.0
MAX_VDW_AMPLITUDE = 100.0
#: Substrate roughness, nm RMS (``[sim] roughness_rms``), and its correlation length, nm
#: (``[sim] roughness_length``): the roughness is a grid of one node per length over the
#: scene's area and a margin of 20 lengths, at most MAX_PIXELS nodes.
MAX_ROUGHNESS = 10.0
MIN_ROUGHNESS_LENGTH = 1.0
MAX_ROUGHNESS_LENGTH = 10_000.0
#: Time XY must rest to end a move, s (``[sim] stop_time``): 1 ms to 10 s.
MIN_STOP_TIME = 0.001
MAX_STOP_TIME = 10.0
