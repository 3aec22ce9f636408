"""The jump of the drift the bootstrap's references measure (:meth:`.scan_drift.ScanDrift.jump_evidence`).

A sudden jump of the drift after the full scan began (a knock, a thermal shock) is the
same for every reference scanned again after it, where a velocity moves each in
proportion to how long ago its row was scanned: the model with a jump ``J`` from some
time on tells the two apart (``docs/execution.md``)."""

from __future__ import annotations

import math

import numpy as np

from .scan_drift import JUMP_CARRIERS, PARAMETERS


def evidence(sd, tears_only: bool = False) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``(J, C_J, Jᵀ C_J⁻¹ J, since)``: the jump of the drift after the full scan began
    that the references measure with ``θ`` (the model with it), its covariance, its Wald
    statistic and the time it counts from (s after the epoch), whichever of these fits
    the references best: the scan's end; a reference's time as it was scanned again (a
    jump then leaves the first ones without it); halfway between two references' rows
    of the full scan (a jump while it was made tears it: the rows after carry it, and
    the references on them are seen where the scan has them; a reference of the drift
    since the scan began, a keep-out's corner, has its row among them). At least
    :data:`JUMP_CARRIERS` references carry a jump while they are scanned again and two
    do not, two carry one at the scan's end, and two carry one in the scan and two not:
    one reference alone before a jump is no evidence of one but a reference the others
    contradict, which the bootstrap's outlier test leaves out (scale1000 seed 1: the
    first reference after a 4000 s scan, in a cluster of three, 110-145 nm off the
    others, read as a jump of 150, -75 nm ± 21 from the second reference's time, with
    a statistic of 56 on a drift without a jump; the run relocalised 20 times). The
    statistic is the least with any one reference left out (:func:`_without_any_one`);
    0 when no reference measured a jump. ``tears_only``: of the times within the scan
    alone."""
    none = np.zeros(2), sd._prior_j[PARAMETERS:, PARAMETERS:].copy(), 0.0, sd.tau_end
    if sd.tau_end is None or not sd._seen:
        return none
    seen = list(sd._seen.values())
    after = sorted({t1 for comps in seen for _, _, t1 in comps})[1:]
    # rows of the full scan: the references' first sightings, and the later ends of those
    # within it (a keep-out corner measures its row's drift since the scan began)
    row_times = sorted({t0 for comps in seen for _, t0, _ in comps}
                       | {t1 for comps in seen for _, _, t1 in comps if t1 <= sd.tau_end})
    best = None
    tears = [0.5 * (a + b) for a, b in zip(row_times, row_times[1:])]
    for since in (tears if tears_only else [sd.tau_end, *after, *tears]):
        carry = sum(any(t0 < since <= t1 for _, t0, t1 in comps) for comps in seen)
        if carry < (JUMP_CARRIERS if since > sd.tau_end else 2) or (since != sd.tau_end and len(seen) - carry < 2):
            continue
        rows, info, eta = sd._split(since)
        if not np.any(info[PARAMETERS:, PARAMETERS:]):
            continue
        x, J, C, stat = _jump_fit(sd, info, eta)
        chi2 = sum((z - g @ x) ** 2 / var for comps in rows.values() for g, z, var in comps)
        chi2 += float(x @ np.linalg.solve(sd._prior_j, x))
        if best is None or chi2 < best[0]:
            best = (chi2, J, C, stat, since, rows, info, eta)
    if best is None:
        return none
    _, J, C, stat, since, rows, info, eta = best
    return J, C, min(stat, _without_any_one(sd, rows, info, eta)), since


def _jump_fit(sd, info: np.ndarray, eta: np.ndarray):
    """``(x, J, C_J, Wald statistic)`` of the model with the jump from ``info``, ``eta``."""
    cov = np.linalg.inv(np.linalg.inv(sd._prior_j) + info)
    x = cov @ eta
    C = 0.5 * (cov[PARAMETERS:, PARAMETERS:] + cov[PARAMETERS:, PARAMETERS:].T)
    J = x[PARAMETERS:]
    return x, J, C, float(J @ np.linalg.solve(C, J))


def _without_any_one(sd, rows: dict, info: np.ndarray, eta: np.ndarray) -> float:
    """The least Wald statistic of the jump with any one reference left out: a jump
    is evident only when no single reference makes it so. Two references before a
    jump, one of them a neighbour taken for it, would otherwise make one (the
    outlier test comes after the jump's, which it needs: a reference that did not
    see a jump the others saw is an outlier of the model without it)."""
    least = math.inf
    for comps in rows.values():
        g = np.array([c[0] for c in comps])
        w = np.array([1.0 / c[2] for c in comps])
        z = np.array([c[1] for c in comps])
        least = min(least, _jump_fit(sd, info - (g.T * w) @ g, eta - g.T @ (w * z))[3])
    return least


def tear_band(sd) -> tuple[float, float] | None:
    """``(a, b)``: the full scan's rows (s after the epoch) of the references either side
    of the tear in the model, between which it may lie; None without a tear."""
    if not (sd.stepped and sd.tau_end is not None and sd.tau_jump < sd.tau_end):
        return None
    rows = {t0 for comps in sd._seen.values() for _, t0, _ in comps}
    before = [r for r in rows if r < sd.tau_jump]
    after = [r for r in rows if r >= sd.tau_jump]
    return (max(before), min(after)) if before and after else None


def against_torn_scan(sd, z: np.ndarray, R: np.ndarray, normals, taus) -> tuple[np.ndarray, np.ndarray]:
    """Components ``z`` (covariance ``R``) measured along ``normals`` against the full
    scan's rows of ``taus`` (s after the epoch), with the jump of a tear added to those
    on rows after it, and its covariance: their positions carry the jump, as the
    filter's offset does since the bootstrap (mixed seed 9, a tear at 250 s: every
    reference on the rows after it was 300 nm out of place, rejected, and the run
    relocalised for 9800 s)."""
    after = np.array([sd._after(tau) for tau in taus], float)
    if not after.any():
        return z, R
    G = np.asarray(normals, float) * after[:, None]
    return np.asarray(z, float) + G @ sd.jump, np.asarray(R, float) + G @ sd.cov_j[-2:, -2:] @ G.T


def scanned_before(sd, after: float, count: int) -> list[tuple]:
    """The keys of up to ``count`` references scanned again only before ``after`` (s after
    the epoch), with their latest row of the full scan: ``[(key, row)]``, latest row first."""
    rows = {key: max(t0 for _, t0, _ in seen) for key, seen in sd._seen.items()
            if all(t1 < after for _, _, t1 in seen)}
    return sorted(rows.items(), key=lambda kv: -kv[1])[:count]


def jump_text(scan) -> str | None:
    """What jump the bootstrap took into the model ``scan``, said; None where it took none."""
    if not scan.stepped:
        return None
    jump, since = scan.jump, scan.tau_jump
    std = math.sqrt(max(float(np.linalg.eigvalsh(scan.cov_j[-2:, -2:])[-1]), 0.0))
    when = (f"during the full scan, about its row of {since + scan.epoch:.0f} s" if since < scan.tau_end
            else f"after the full scan, before {since + scan.epoch:.0f} s")
    return f"the drift jumped by {jump[0]:+.0f}, {jump[1]:+.0f} nm (± {std:.1f}) {when}: taken into the model"
