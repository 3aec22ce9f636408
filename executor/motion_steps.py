"""Moves as plan stubs: lifted travel, lifting the tip, and a push streamed to the DAC with
drift folded in and its signals watched.

Free generator functions over a :class:`~nanoasm.executor.context.RunContext`; every move
is within the instrument's slew limits (:func:`nanoasm.instrument.ramp` and
:func:`nanoasm.executor.dac.plan_dac`) and is told to the drift estimator, whose creep
model follows it.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from nanoasm.planner import Operation
from nanoasm.world.cantilever import Cantilever

from .contact_angle import MIN_FORCE, PushSignals
from .contact_load import preload_cap
from .context import RunContext
from .dac import plan_dac
from .progress_docs import PROGRESS, ProgressDoc
from .engine import Msg
from .monitor import PushMonitor, Verdict
from .trajectory import PUSH, TRAVEL, operation

#: A scan line starting farther than this (nm) from the tip is preceded by a travel.
APPROACH = 300.0
#: Every this many samples of a streamed chunk go to the run log.
DAC_LOG_EVERY = 50
#: DAC samples per chunk of a tracked push (its contact angle is read after each): 0.1 s
#: at the default 1 kHz, 20 nm at 200 nm/s.
TRACK_CHUNK = 100


def travel_to(ctx: RunContext, xy):
    """Lifted travel to ``xy`` (scanner frame nm) within the slew limit."""
    from nanoasm.instrument import ramp

    cfg = ctx.config
    here = yield Msg("position")
    there = cfg.nm_to_codes(np.array([xy[0], xy[1], cfg.lift]))
    path = ramp(here, there, cfg)
    if len(path):
        block = yield Msg("write", (path,))
        ctx.ledger.times["travel"] += len(block) / cfg.sample_rate
        _moved(ctx, here, path, block.t, [len(path) - 1])


def _in_range(cfg, xy) -> np.ndarray:
    """``xy`` (scanner frame nm) clipped to the scanner's XY range."""
    return np.clip(np.asarray(xy, float), cfg.lower[:2], cfg.upper[:2])


def approach(ctx: RunContext, xy):
    """Travel (lifted, recorded for creep) to a scan line that starts far from the tip,
    so the scan itself is a small move."""
    here = yield Msg("position")
    there = ctx.config.codes_to_nm(np.asarray(here))[:2]
    if math.dist(there, xy) > APPROACH:
        yield from travel_to(ctx, _in_range(ctx.config, xy))


def lift(ctx: RunContext):
    """Stop a push: lift the tip straight up within the slew limit."""
    from nanoasm.instrument import ramp

    cfg = ctx.config
    here = yield Msg("position")
    up = np.asarray(here).copy()
    up[2] = cfg.nm_to_codes(np.array([0.0, 0.0, cfg.lift]))[2]
    path = ramp(here, up, cfg)
    if len(path):
        block = yield Msg("write", (path,))
        ctx.ledger.times["travel"] += len(block) / cfg.sample_rate


def _moved(ctx: RunContext, start_codes, codes, t, rests) -> None:
    """Tell the drift estimator about the scanner's motion from ``start_codes`` (where the
    path began) through the samples ``codes`` played at ``t``, at rest at the indices
    ``rests``: creep follows its pieces as it goes, and its ends where XY stops."""
    cfg = ctx.config
    ctx.drift.moved_along(cfg.codes_to_nm(np.asarray(codes))[:, :2], t,
                          start=cfg.codes_to_nm(np.asarray(start_codes))[:2], rests=rests)


def dac_doc(ctx: RunContext, codes, kind, block, every: int = DAC_LOG_EVERY) -> dict:
    """A streamed DAC chunk, every ``every``-th sample: scanner nm, kind, signals."""
    nm = ctx.config.codes_to_nm(np.asarray(codes)[::every])
    return {"t": block.t[::every].tolist(), "x": nm[:, 0].tolist(), "y": nm[:, 1].tolist(),
            "z": nm[:, 2].tolist(), "kind": np.asarray(kind)[::every].tolist(),
            "s_n": block.s_n[::every].tolist(), "s_l": block.s_l[::every].tolist(),
            "n": int(len(codes)), "every": every}


def stream_push(ctx: RunContext, op: Operation, lever: Cantilever, preload_factor: float = 1.0,
                lead: float | None = None, track: float | None = None, blind: float = math.inf,
                capture: float = 90.0):
    """Travel to the push, lower, push, lift; watching the signals. Returns the verdict.

    The tip is pressed with ``preload_factor`` times the instrument's preload (seed eq.
    4.7: the normal force that keeps the tip down on the object, :mod:`.contact_load`,
    more after a slip over it), up to
    :func:`~.contact_load.preload_cap`. With ``lead`` (nm the tip slides in contact
    before it meets the object) the verdict says where the object sat on the tip at the
    end (:mod:`.contact_angle`). With ``track`` (degrees, and ``lead``) that angle is read
    after every chunk of :data:`TRACK_CHUNK` samples, and the push is stopped and the tip
    lifted once it passes ``track``: the object is sliding off the tip (the verdict's
    ``stopped`` says where the tip was); so it is too where the tip has gone ``blind`` nm
    from the path's start with no angle to read, and the verdict's ``felt`` says whether
    anything pressed on the tip then (more than :data:`~.contact_angle.MIN_FORCE` beyond
    its own friction; a particle of low friction carried may not). Stopped at an angle
    beyond ``capture`` (the object is not carried), the push has lost its object: "slipped"."""
    cfg = ctx.config
    if preload_factor != 1.0:
        cfg = replace(cfg, preload=min(cfg.preload * preload_factor, preload_cap(cfg, lever)))
    switch = ctx.timing.switch_ahead()
    if switch > 0.0:
        # after scanning, the instrument switches into contact before the first write that
        # touches down: lifted to the path's start first, so that the switch comes before
        # the push, whose samples are then timed from its end (timed from before it, the
        # drift folded into the path was that of ``switch`` seconds too early: on scale1000
        # seed 1 the sample drifted 26 nm in those 2 s (median; 144 nm at the 90th
        # percentile), more than a correction push's 15 nm)
        t = yield Msg("clock")
        yield from travel_to(ctx, _in_range(cfg, np.asarray(op.tip_path[0], float) + ctx.offset(t)))
    current = yield Msg("position")
    t0 = yield Msg("clock")
    t_first = t0 + switch
    moves = operation(op.tip_path, push_speed=ctx.options.push_speed)
    dac = plan_dac(moves, cfg, current, t0=t_first, drift=ctx.drift.predicted(t_first), lever=lever)
    pending = ctx.drift.pending_moves(dac, current, ctx.config)
    if pending:     # the path creeps as it goes (its travel, then the push): follow it
        dac = plan_dac(moves, cfg, current, t0=t_first, drift=ctx.drift.predicted(t_first, pending), lever=lever)
    monitor = PushMonitor(cfg.preload, lever=lever, force_limit=ctx.options.force_limit, baselines=ctx.baselines,
                          friction=ctx.options.substrate_friction)
    verdict = None
    kept = None if lead is None else PushSignals(lead)
    tracked = track is not None and kept is not None
    path = np.asarray(op.tip_path, float)
    stop_at, stop_angle = None, None    # where a tracked push was stopped short, and its angle
    pressing = True                     # a blind stop's chunk pressed on an object
    n_push = n_other = 0
    # creep follows the path in pieces as it goes, and its moves end where XY rests
    rests = dac.profile.rests()
    for chunk in dac.chunks(min(ctx.options.chunk, TRACK_CHUNK) if tracked else ctx.options.chunk):
        block = yield Msg("write", (chunk.codes,))
        yield Msg("emit", ("dac", dac_doc(ctx, chunk.codes, chunk.kind, block)))
        lifted = chunk.kind == TRAVEL                              # travel: free air
        if lifted.any() and not monitor.in_contact:
            monitor.set_baseline(block.s_n[lifted], block.s_l[lifted])
        pushing = chunk.kind == PUSH
        n_push += int(pushing.sum())
        n_other += int((~pushing).sum())
        xy = cfg.codes_to_nm(chunk.codes)[:, :2] if kept is not None or pushing.any() else None
        if kept is not None:
            kept.add(block.s_n, block.s_l, xy, pushing, lifted)
        if pushing.any():
            v = monitor.check(block.s_n[pushing], block.s_l[pushing], xy[pushing])
            verdict = v if v.failed else None
            if tracked and verdict is None:
                angle = kept.angle(monitor.compensated, monitor.level, path[-1] - path[-2], cfg.scan_angle, lever,
                                   key=monitor.baseline_key)
                end = chunk.first + len(chunk) - 1
                if angle is not None and abs(angle.angle) >= track:
                    stop_at, stop_angle = end, angle
                elif angle is None and math.dist(dac.profile.sample(np.array([end]))[0][0, :2], path[0]) > blind:
                    stop_at = end
                    f_n, f_l = monitor.forces(block.s_n[pushing], block.s_l[pushing], xy[pushing])
                    pressing = float(np.mean(np.abs(f_l) - monitor.friction * np.maximum(f_n, 0.0))) >= MIN_FORCE
        here = rests[(rests >= chunk.first) & (rests < chunk.first + len(chunk))] - chunk.first
        stop = verdict is not None or stop_at is not None
        _moved(ctx, current, chunk.codes, block.t, np.append(here, len(chunk) - 1) if stop else here)
        if stop:                        # stopped here: lifted where it is
            break
    # what the instrument took beyond the samples streamed: the approach into contact
    t_end = yield Msg("clock")
    extra = max(t_end - t0 - (n_push + n_other) / cfg.sample_rate, 0.0)
    ctx.ledger.times["mode_switch"] += extra
    ctx.timing.pushed(extra)
    if verdict is None:
        verdict = monitor.finish()
    if stop_at is not None and stop_angle is not None and abs(stop_angle.angle) >= capture:
        verdict = Verdict("slipped", None, verdict.peak_force)      # the object is not on the tip
    elif stop_at is not None:           # the object sliding off: stopped where the tip was
        at = dac.profile.sample(np.array([stop_at]))[0][0, :2]
        verdict = replace(verdict, contact=stop_angle, stopped=(float(at[0]), float(at[1])),
                          felt=stop_angle is not None or pressing)
    elif kept is not None and not verdict.failed:
        verdict = replace(verdict, contact=kept.angle(monitor.compensated, monitor.level, path[-1] - path[-2],
                                                      cfg.scan_angle, lever, key=monitor.baseline_key))
    if verdict.failed or stop_at is not None:
        yield from lift(ctx)
    ctx.ledger.times["push"] += n_push / cfg.sample_rate
    ctx.ledger.times["travel"] += n_other / cfg.sample_rate
    length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    towards = f"towards {op.target}" if op.target is not None else "out of the way"
    short = "" if stop_at is None else ", stopped short: no contact angle" if stop_angle is None else \
        f", stopped short with the object {stop_angle.angle:+.0f}° round the tip"
    yield Msg("emit", (PROGRESS, ProgressDoc("push", f"{op.object} {towards}, {length:.0f} nm of tip path at "
                                                     f"{cfg.preload * lever.spring_constant:.0f} nN: {verdict.status} "
                                                     f"(peak force {verdict.peak_force:.0f} nN){short}")))
    return verdict
