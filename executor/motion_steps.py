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

from .contact_angle import PushSignals
from .context import RunContext
from .dac import plan_dac
from .progress_docs import PROGRESS, ProgressDoc
from .engine import Msg
from .monitor import PushMonitor
from .trajectory import PUSH, TRAVEL, operation

#: A scan line starting farther than this (nm) from the tip is preceded by a travel.
APPROACH = 300.0
#: A preload raised for an object the tip slipped over stays within this share of the Z range.
PRELOAD_CAP = 0.45
#: Every this many samples of a streamed chunk go to the run log.
DAC_LOG_EVERY = 50


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


def approach(ctx: RunContext, xy):
    """Travel (lifted, recorded for creep) to a scan line that starts far from the tip,
    so the scan itself is a small move."""
    here = yield Msg("position")
    there = ctx.config.codes_to_nm(np.asarray(here))[:2]
    if math.dist(there, xy) > APPROACH:
        lo, hi = ctx.config.lower[:2], ctx.config.upper[:2]
        yield from travel_to(ctx, np.clip(np.asarray(xy, float), lo, hi))


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
                lead: float | None = None):
    """Travel to the push, lower, push, lift; watching the signals. Returns the verdict.

    An object the tip slipped over before is pushed with ``preload_factor`` times the
    preload (seed eq. 4.7: a larger normal force keeps the tip down), up to
    :data:`PRELOAD_CAP` of the Z range. With ``lead`` (nm the tip slides in contact
    before it meets the object) the verdict says where the object sat on the tip at the
    end (:mod:`.contact_angle`)."""
    cfg = ctx.config
    if preload_factor != 1.0:
        cfg = replace(cfg, preload=min(cfg.preload * preload_factor, PRELOAD_CAP * cfg.z_range))
    current = yield Msg("position")
    t0 = yield Msg("clock")
    moves = operation(op.tip_path, push_speed=ctx.options.push_speed)
    dac = plan_dac(moves, cfg, current, t0=t0, drift=ctx.drift.predicted(t0), lever=lever)
    pending = ctx.drift.pending_moves(dac, current, ctx.config)
    if pending:     # the path creeps as it goes (its travel, then the push): follow it
        dac = plan_dac(moves, cfg, current, t0=t0, drift=ctx.drift.predicted(t0, pending), lever=lever)
    monitor = PushMonitor(cfg.preload, lever=lever, force_limit=ctx.options.force_limit, baselines=ctx.baselines,
                          friction=ctx.options.substrate_friction)
    verdict = None
    kept = None if lead is None else PushSignals(lead)
    n_push = n_other = 0
    # creep follows the path in pieces as it goes, and its moves end where XY rests
    rests = dac.profile.rests()
    for chunk in dac.chunks(ctx.options.chunk):
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
        here = rests[(rests >= chunk.first) & (rests < chunk.first + len(chunk))] - chunk.first
        _moved(ctx, current, chunk.codes, block.t, here if verdict is None else np.append(here, len(chunk) - 1))
        if verdict is not None:         # stopped here: lifted where it is
            break
    # what the instrument took beyond the samples streamed: the approach into contact
    t_end = yield Msg("clock")
    ctx.ledger.times["mode_switch"] += max(t_end - t0 - (n_push + n_other) / cfg.sample_rate, 0.0)
    if verdict is None:
        verdict = monitor.finish()
    path = np.asarray(op.tip_path, float)
    if kept is not None and not verdict.failed:
        verdict = replace(verdict, contact=kept.angle(monitor.compensated, monitor.level, path[-1] - path[-2],
                                                      cfg.scan_angle, lever))
    if verdict.failed:
        yield from lift(ctx)
    ctx.ledger.times["push"] += n_push / cfg.sample_rate
    ctx.ledger.times["travel"] += n_other / cfg.sample_rate
    length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    towards = f"towards {op.target}" if op.target is not None else "out of the way"
    yield Msg("emit", (PROGRESS, ProgressDoc("push", f"{op.object} {towards}, {length:.0f} nm of tip path: "
                                                     f"{verdict.status} (peak force {verdict.peak_force:.0f} nN)")))
    return verdict
