"""An AFM driven by a Nanonis controller: the :class:`~nanoasm.instrument.Instrument`
protocol over its TCP programming interface (``nanonis-spm``, :mod:`.nanonis_link`).

What the backend assumes of the controller and the lab:

- Before the run the operator engages the tip on the substrate (Z controller on, in
  tapping or contact feedback at its setpoint). The backend takes the surface from the
  Z it holds there (``ZCtrl.ZPosGet``), then parks: Z controller off, Z to the top of
  the scanner frame, XY to the centre of the travel.
- Nanonis Z grows away from the sample (``ZCtrl.Withdraw`` goes to the upper limit).
  Scanner-frame ``z`` nm is Nanonis Z = surface + z; the frame's Z range
  ``[-z_range/2, z_range/2]`` about the surface must lie within the controller's Z
  limits (``ZCtrl.LimitsGet``), which is checked whenever the surface is taken.
- Scanner-frame XY ``(x, y)`` nm is Nanonis XY ``(x, y) - xy_range/2 + [nanonis] centre``,
  which must lie within the piezo's range about Nanonis XY 0 (``Piezo.RangeGet``).

How each command is done, and what is approximated:

- ``write`` (a streamed tip path): the chunk passes :func:`~nanoasm.instrument.check_samples`
  first; then, with the Z controller off, it is played as straight legs
  (:mod:`.nanonis_path`): follow-me XY moves (``FolMe.SpeedSet``, ``FolMe.XYPosSet``
  waiting for the end of the move) and Z moves in steps of at most ``[nanonis] z_step``
  (``ZCtrl.ZPosSet``) paced at the leg's speed. Legs are at most ``[nanonis] leg`` nm
  long where they reach the surface and ``lifted_leg`` nm where they do not.
  *Approximated:* a leg moves at one speed (the path's own timing within a leg is not
  kept, and the tip stops between legs); a leg that moves XY and Z together goes Z-up
  then XY, or XY then Z-down, so the tip travels at the higher of its two heights; S_n
  and S_l are read once at the end of each leg (``Signals.ValsGet``) and stand for
  every sample of the leg (a force curve or a baseline map has one value a leg); a
  sample's time is interpolated between the leg's start and end.
- ``scan_line``: lifted travel to ``a``, Z controller on (engage), ``[imaging] settle``,
  then at each of the ``n`` points a follow-me move at ``line_speed`` and a read of Z;
  heights are Z minus the surface in nm. Then Z controller off and lift.
- ``full_scan``: the scan module: ``Scan.FrameSet``, ``Scan.BufferSet`` (the Z slot
  ``[nanonis] scan_channel``), ``Scan.SpeedSet``, ``Scan.Action`` start upwards,
  ``Scan.WaitEndOfScan``, ``Scan.FrameDataGrab`` (forward). Row 0 of the grabbed frame
  is taken as the first line scanned (the bottom one scanning up; flipped if the
  controller reports a downward scan). The scan module rounds pixels to a multiple
  of 16; the frame is then resampled to ``pixels`` x ``pixels``.
- After each scan line and full scan the surface is taken again, as the 10th
  percentile of the heights just measured (so that pushes follow the sample's Z
  drift; a scan line that would move it by more than 30 nm is ignored, taken for one
  along an object); heights are returned relative to the surface as it was before.
- Time is the host's monotonic clock since the backend opened.

Every exit parks: use it as a context manager. A lost connection (a timeout, the
controller gone) closes the link; :meth:`NanonisInstrument.park` reconnects once, reads
where the tip is and parks from there.
"""

from __future__ import annotations

import math
import time
from typing import Self

import numpy as np

from nanoasm.errors import InstrumentLimitError
from nanoasm.instrument import HeightImage, InstrumentConfig, Region, SignalBlock, check_samples

from .instrument_file import InstrumentFile
from .nanonis_link import NanonisError, NanonisLink
from .nanonis_path import legs
from .scan_args import count, resample, scan_square, scanner_xy

#: The percentile of a scan's heights taken as the substrate when the surface is taken again.
SURFACE_PERCENTILE = 10.0
#: A scan line moving the surface by more than this (nm) ran on an object along most of its
#: length: its shift is ignored (Z drift moves the surface by far less between two lines).
SURFACE_STEP = 30.0


class NanonisInstrument:
    """The :class:`~nanoasm.instrument.Instrument` of an AFM behind a Nanonis controller.

    Parameters
    ----------
    config : InstrumentFile
        A loaded instrument file with ``backend = "nanonis"``.
    nanonis_module : module, optional
        ``nanonis_spm`` or a stand-in (tests); default: import it.
    clock, sleep : callables, optional
        Host time (s) and waiting; default :func:`time.monotonic` and :func:`time.sleep`.

    Raises
    ------
    NanonisError
        The package is missing, the controller is unreachable, refuses a command, its Z
        controller is off, or the scanner frame does not fit its Z limits or holds the tip.
    """

    def __init__(self, config: InstrumentFile, *, nanonis_module=None, clock=time.monotonic, sleep=time.sleep):
        if not isinstance(config, InstrumentFile) or config.nanonis is None:
            raise TypeError("config must be an InstrumentFile with backend = 'nanonis'")
        self.file, self.net = config, config.nanonis
        self._now, self._sleep = clock, sleep
        self._t0 = clock()
        self._signals = (0.0, 0.0)
        self._speed: float | None = None   # follow-me speed last set, nm/s
        self._engaged = self._scanning = False
        self._pos = np.zeros(3)            # commanded tip position, scanner frame nm
        self._last = config.scanner.rest_codes()
        self._link = NanonisLink(self.net, module=nanonis_module)
        try:
            self._start()
            self.park()
        except BaseException:
            self._link.close()
            raise

    # -- the Instrument protocol ---------------------------------------------------------------
    @property
    def config(self) -> InstrumentConfig:
        return self.file.scanner

    def clock(self) -> float:
        """Host seconds since the backend opened (monotonic)."""
        return self._now() - self._t0

    def position(self) -> np.ndarray:
        return self._last.copy()

    def signals(self) -> tuple[float, float]:
        """``(S_n, S_l)`` read now; once the link is closed, the last ones read."""
        if self._link.connected:
            self._signals = self._read_signals()
        return self._signals

    def write(self, chunk: np.ndarray) -> SignalBlock:
        """Play an ``(n, 3)`` chunk of XYZ codes (checked first) as follow-me legs with the
        Z controller off; S_n, S_l of each sample are those read at the end of its leg."""
        cfg = self.config
        codes = check_samples(chunk, cfg, previous=self._last)
        nm = cfg.codes_to_nm(codes)
        self._release()
        n = codes.shape[0]
        t, s_n, s_l = np.empty(n), np.empty(n), np.empty(n)
        tol = float(cfg.nm_per_code.max())
        t_prev = self.clock()
        for leg in legs(self._pos, nm, tol, self.net.leg, self.net.lifted_leg):
            self._leg(leg.target, leg.samples / cfg.sample_rate)
            sig = self._read_signals()
            t_end = self.clock()
            k = np.arange(1, leg.samples + 1) / leg.samples
            t[leg.first:leg.stop] = t_prev + k * (t_end - t_prev)
            s_n[leg.first:leg.stop], s_l[leg.first:leg.stop] = sig
            t_prev = t_end
            self._last = codes[leg.stop - 1].copy()
        self._signals = (float(s_n[-1]), float(s_l[-1]))
        return SignalBlock(t, s_n, s_l)

    def scan_line(self, a: tuple[float, float], b: tuple[float, float], n: int) -> np.ndarray:
        """Heights (nm) at ``n`` points from ``a`` to ``b``: lifted travel, engage, settle,
        a follow-me move and a Z read at each point at ``[imaging] line_speed``, lift."""
        n = count("n", n)
        pa, pb = scanner_xy(self.config, "a", a), scanner_xy(self.config, "b", b)
        self._travel(pa)
        self._engage()
        out = np.empty(n)
        for i, p in enumerate(np.linspace(pa, pb, n)):
            if i:
                self._xy_to(p, self.file.imaging.line_speed)
            out[i] = self._read_z()
        self._resurface(out, SURFACE_STEP)
        self._lift()
        return out

    def full_scan(self, pixels: int, region: Region | None = None) -> HeightImage:
        """A ``pixels`` x ``pixels`` image of the square of side max(width, height) at the
        region's lower-left corner (default: the largest square of the XY range at the
        origin), scanned upwards by the scan module; the tip ends lifted."""
        pixels = count("pixels", pixels)
        x0, y0, side = scan_square(self.config, region)
        speed = self.file.imaging.full_scan_speed
        self._travel(np.array([x0, y0]))
        self._engage()
        cx, cy = self._nanonis_xy((x0 + side / 2, y0 + side / 2))
        call = self._link.call
        call("Scan_FrameSet", cx, cy, side * 1e-9, side * 1e-9, 0.0)
        call("Scan_BufferSet", [self.net.scan_channel], pixels, pixels)
        call("Scan_SpeedSet", speed * 1e-9, speed * 1e-9, 0.0, 0.0, 1, 1.0)
        self._scanning = True
        call("Scan_Action", 0, 1)
        duration = 2.0 * pixels * side / speed
        timed_out = call("Scan_WaitEndOfScan", round((duration + self.net.timeout) * 1e3), duration=duration)[0]
        if timed_out:
            raise NanonisError(f"Scan.WaitEndOfScan: the scan did not end within {duration + self.net.timeout:.0f} s")
        call("Scan_Action", 1, 1)
        self._scanning = False
        *_, data, direction = call("Scan_FrameDataGrab", self.net.scan_channel, 1)
        self._read_xy(strict=False)
        frame = np.asarray(data, float) * 1e9 - self._surface
        height = resample(frame if direction == 1 else frame[::-1], pixels)
        self._resurface(height)
        self._lift()
        return HeightImage(height, side / pixels, (x0, y0), source=f"nanonis:{self.net.address}",
                           meta={"speed": speed, "trace": "left to right, rows bottom up"})

    def park(self) -> None:
        """Z controller off, Z to the top of the frame, XY to rest (both at ``max_speed``).

        Idempotent: parked (even closed), it sends nothing. A closed link (a lost
        controller, Ctrl-C in the middle of a reply) is opened again and the tip parked
        from where it is.
        """
        cfg = self.config
        rest = cfg.rest_codes()
        if not (self._engaged or self._scanning) and np.array_equal(self._last, rest):
            return
        if not self._link.connected:
            self._link.reconnect()
            self._resync()
        if self._scanning:
            self._link.call("Scan_Action", 1, 1)
            self._scanning = False
        self._release()
        target = cfg.codes_to_nm(rest)
        self._z_to(target[2], cfg.max_speed)
        self._xy_to(target[:2], cfg.max_speed)
        self._last = rest.copy()

    def close(self) -> None:
        """Park, and close the link whatever happens."""
        try:
            self.park()
        finally:
            self._link.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    # -- start and state ---------------------------------------------------------------------
    def _start(self) -> None:
        call = self._link.call
        high, low = call("ZCtrl_LimitsGet")
        self._zlim = (low * 1e9, high * 1e9)
        if not call("ZCtrl_OnOffGet")[0]:
            raise NanonisError("the Nanonis Z controller is off: engage the tip on the substrate before the run "
                               "(the backend takes the surface from the Z it holds there)")
        if call("Scan_StatusGet")[0]:
            raise NanonisError("the Nanonis scan module is scanning: stop the scan before the run")
        self._check_xy_range(call("Piezo_RangeGet")[:2])
        if self.net.setpoint is not None:
            call("ZCtrl_SetpntSet", float(self.net.setpoint))
            self._sleep(self.file.imaging.settle)
        self._engaged = True
        self._surface = 0.0
        self._set_surface(self._read_z())
        self._read_xy()
        self._pos[2] = 0.0

    def _check_xy_range(self, piezo) -> None:
        """The scanner frame's XY (about ``[nanonis] centre``) within the piezo's range (m)."""
        half = np.asarray(self.config.xy_range) / 2
        reach = np.abs(np.asarray(self.net.centre)) + half
        if np.any(reach > np.asarray(piezo) * 1e9 / 2 * (1 + 1e-6)):
            raise NanonisError(f"the scanner frame, [nanonis] centre ± [scanner] xy_range / 2, reaches "
                               f"±({reach[0]:.0f}, {reach[1]:.0f}) nm, beyond the piezo's XY range "
                               f"±({piezo[0] * 5e8:.0f}, {piezo[1] * 5e8:.0f}) nm")

    def _resync(self) -> None:
        """Read the controller's state after a reconnect: scan, Z controller, Z, XY."""
        call = self._link.call
        self._speed = None
        self._scanning = bool(call("Scan_StatusGet")[0])
        self._engaged = bool(call("ZCtrl_OnOffGet")[0])
        self._pos[2] = self._read_z()
        self._read_xy(strict=False)

    def _set_surface(self, z: float) -> None:
        """Take the surface at scanner-frame ``z`` (nm) of the present surface."""
        lo, hi = self._zlim
        surface = self._surface + z
        half = self.config.z_range / 2
        if surface - half < lo - 1e-6 or surface + half > hi + 1e-6:
            raise NanonisError(f"the Z range of [scanner] z_range = {self.config.z_range:g} nm about the surface at "
                               f"Z = {surface:.0f} nm leaves the controller's Z limits [{lo:.0f}, {hi:.0f}] nm: "
                               "lower z_range or engage nearer the middle of the Z range")
        self._pos[2] -= surface - self._surface
        self._surface = surface

    def _resurface(self, heights: np.ndarray, limit: float = math.inf) -> None:
        finite = heights[np.isfinite(heights)]
        if finite.size and abs(shift := float(np.percentile(finite, SURFACE_PERCENTILE))) <= limit:
            self._set_surface(shift)

    # -- moves ---------------------------------------------------------------------------------
    def _leg(self, target: np.ndarray, duration: float) -> None:
        """One straight leg from the present position; Z first when it rises."""
        d = target - self._pos
        dxy, dz = math.hypot(d[0], d[1]), abs(d[2])
        if dxy == 0 and dz == 0:
            self._sleep(duration)
            return
        speed = min(max(dxy, dz) / duration, self.config.max_speed)
        if d[2] > 0:
            self._z_to(target[2], speed)
        if dxy:
            self._xy_to(target[:2], speed)
        if d[2] < 0:
            self._z_to(target[2], speed)

    def _z_to(self, z: float, speed: float) -> None:
        """Z controller off: Z to ``z`` nm in steps of at most ``z_step``, at ``speed`` nm/s."""
        z0 = self._pos[2]
        if z == z0:
            return
        lo, hi = self.config.lower[2], self.config.upper[2]
        if not lo - 1e-6 <= z <= hi + 1e-6:
            raise InstrumentLimitError(f"z = {z:.1f} nm outside the scanner range [{lo:g}, {hi:g}] nm; nothing sent")
        steps = math.ceil(abs(z - z0) / self.net.z_step)
        t0 = self._now()
        for k in range(1, steps + 1):
            zk = z0 + (z - z0) * k / steps
            self._sleep(max(0.0, t0 + abs(zk - z0) / speed - self._now()))
            self._link.call("ZCtrl_ZPosSet", (self._surface + zk) * 1e-9)
            self._pos[2] = zk

    def _xy_to(self, xy: np.ndarray, speed: float) -> None:
        """A follow-me move to ``xy`` (scanner nm) at ``speed`` nm/s, waiting for its end."""
        xy = np.asarray(xy, float)
        hi = self.config.upper[:2]
        if np.any(xy < -1e-6) or np.any(xy > hi + 1e-6):
            raise InstrumentLimitError(f"({xy[0]:g}, {xy[1]:g}) nm outside the scanner range; nothing sent")
        speed = min(float(speed), self.config.max_speed)
        if speed != self._speed:
            self._link.call("FolMe_SpeedSet", speed * 1e-9, 1)
            self._speed = speed
        distance = math.dist(xy, self._pos[:2])
        self._link.call("FolMe_XYPosSet", *self._nanonis_xy(xy), 1, duration=distance / speed)
        self._pos[:2] = xy

    def _release(self) -> None:
        """Z controller off; Z stays where the controller held it."""
        if self._engaged:
            self._link.call("ZCtrl_OnOffSet", 0)
            self._engaged = False
            self._pos[2] = self._read_z()

    def _engage(self) -> None:
        self._link.call("ZCtrl_OnOffSet", 1)
        self._engaged = True
        self._sleep(self.file.imaging.settle)
        self._pos[2] = self._read_z()

    def _lift(self) -> None:
        """Z controller off and Z to at least ``lift``; the DAC position follows."""
        self._release()
        self._z_to(max(self._pos[2], self.config.lift), self.config.max_speed)
        self._last = self._codes()

    def _travel(self, xy: np.ndarray) -> None:
        """Lift, then a follow-me move to ``xy`` at ``max_speed``."""
        self._lift()
        self._xy_to(xy, self.config.max_speed)
        self._last = self._codes()

    # -- reads and frames ---------------------------------------------------------------------
    def _read_signals(self) -> tuple[float, float]:
        _, values = self._link.call("Signals_ValsGet", [self.net.normal, self.net.lateral], 1)
        return float(values[0][0]), float(values[1][0])

    def _read_z(self) -> float:
        """Scanner-frame z (nm) of the tip now."""
        return self._link.call("ZCtrl_ZPosGet")[0] * 1e9 - self._surface

    def _read_xy(self, strict: bool = True) -> None:
        """Where the tip is in XY; outside the frame an error (``strict``) or clipped to it."""
        x, y = self._link.call("FolMe_XYPosGet", 1)
        half = np.asarray(self.config.xy_range) / 2
        xy = np.array([x, y]) * 1e9 + half - np.asarray(self.net.centre)
        if not strict:
            xy = np.clip(xy, 0.0, 2 * half)
        elif np.any(xy < -1e-6) or np.any(xy > 2 * half + 1e-6):
            raise NanonisError(f"the tip is at Nanonis XY ({x * 1e9:.0f}, {y * 1e9:.0f}) nm, outside the scanner "
                               f"frame of the instrument file ([nanonis] centre ± [scanner] xy_range / 2)")
        self._pos[:2] = xy

    def _nanonis_xy(self, xy) -> tuple[float, float]:
        half = np.asarray(self.config.xy_range) / 2
        x, y = (np.asarray(xy, float) - half + np.asarray(self.net.centre)) * 1e-9
        return float(x), float(y)

    def _codes(self) -> np.ndarray:
        cfg = self.config
        return cfg.nm_to_codes(np.clip(self._pos, cfg.lower, cfg.upper))


__all__ = ["NanonisError", "NanonisInstrument"]
