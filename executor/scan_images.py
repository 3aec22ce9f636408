"""Images made of local-scan lines or by the instrument's own raster: the window a
relocalisation registers (:func:`scan_window`) and the small drift-compensated images
that look at a crowded particle (:func:`raster`), made with :mod:`.scan_steps`'s lines."""

from __future__ import annotations

import numpy as np

from .context import RunContext
from .engine import Msg
from .progress_docs import PROGRESS, ProgressDoc
from .scan_lines import ScanLine
from .scan_steps import run_pattern


def scan_window(ctx: RunContext, pixels: int, region, what: str):
    """A raster image of ``region`` (scanner frame: x0, y0, x1, y1) of ``pixels`` lines
    of ``pixels`` (plan stub), counted as a local scan and reported as ``what``; returns
    the image and the time it ended."""
    t0 = yield Msg("clock")
    scan = yield Msg("full_scan", (pixels, tuple(float(v) for v in region)))
    t1 = yield Msg("clock")
    ctx.timing.tapping = True
    ctx.ledger.times["local_scan"] += t1 - t0
    ctx.ledger.counts["local_scans"] += 1
    yield Msg("emit", (PROGRESS, ProgressDoc("local scan", f"{what}, {pixels} x {pixels} px, {t1 - t0:.1f} s")))
    return scan, t1


def raster(ctx: RunContext, corner, pixels: int, pixel: float, what: str):
    """A drift-compensated image (plan stub): ``pixels`` scan lines of ``pixels`` samples
    ``pixel`` nm apart, its lower-left corner at ``corner`` (scanner frame, now), every
    other line scanned back the other way. Each line is a local-scan line, placed where
    the drift estimate predicts its row when it is scanned (:func:`.scan_steps.scan_line`), so creep
    right after a travel neither draws the content out nor carries it past the rows (as
    fast as the slow scan on ``scale300``, where a raster of the instrument's own showed
    no particle); and a line of 21 samples costs a fifth of a full-scan line.

    Returns the heights (rows from the bottom, nm), the image's lower-left corner in the
    layout frame and the time its content is of, and counts one local scan, ``what``."""
    x0, y0 = (float(v) for v in corner)
    xa, xb = x0 + 0.5 * pixel, x0 + (pixels - 0.5) * pixel

    def pattern():
        rows = []
        for r in range(pixels):
            y = y0 + (r + 0.5) * pixel
            ends = ((xa, y), (xb, y)) if r % 2 == 0 else ((xb, y), (xa, y))
            profile = np.asarray((yield ScanLine(*ends, pixels, "image")), float)
            rows.append(profile if r % 2 == 0 else profile[::-1])
        return np.array(rows)

    heights = yield from run_pattern(ctx, pattern(), what)
    return heights, np.array([x0, y0]) - ctx.offset(ctx.scan_ref), ctx.scan_ref
