"""Which of the bootstrap's references to leave out: the fewest whose removal leaves every
other one within the gate (:func:`left_out`).

One at a time, the reference the others contradict most is not always the bad one: a
neighbour taken for a reference pulls the fit toward itself, and good references then
look worse than it does. A greedy test left out three good references of `allpushed`
seed 2 (o1, o7 and the edge e3) and kept the one a widened search had taken from a
neighbour (o3). Here every set of up to ``most`` references is tried out together, and
the smallest set that leaves a consistent model is taken, the one whose model fits what
remains best (a consensus, as RANSAC's, over all subsets: a bootstrap has a handful of
references, so trying each is cheap).
"""

from __future__ import annotations

from itertools import combinations
from typing import Callable

import numpy as np

from nanoasm.drift import gate_threshold

from .scan_drift import PARAMETERS, ScanDrift


def consistent(scan: ScanDrift, p: float) -> bool:
    """Every reference of ``scan`` within the gate of probability ``p`` against what
    the others say (its χ² with one degree of freedom a component)."""
    return all(scan.disagreement(k) <= gate_threshold(len(rows), p) for k, rows in scan.rows.items())


def misfit(scan: ScanDrift) -> float:
    """χ² of the references' components against the model ``scan`` holds (the jump's
    columns counted where it is in the model), plus the prior's term."""
    k = PARAMETERS + 2 if scan.stepped else PARAMETERS
    x = np.concatenate([scan.theta, scan.jump])[:k]
    total = sum((z - h[:k] @ x) ** 2 / var for rows in scan.rows.values() for h, z, var in rows)
    return float(total + x @ np.linalg.solve(scan._prior_j[:k, :k], x))


def left_out(scan: ScanDrift, aside: dict, p: float, most: int, settle: Callable[[ScanDrift], None],
             keep: int = 3) -> tuple[list, list]:
    """``(keys to leave out of scan, keys in aside to take back)``: the references,
    those of ``scan`` and those left out before (``aside``: key -> what
    :meth:`ScanDrift.remove` returned), of which the fewest are left out (at most
    ``most`` more than ``aside`` holds, leaving at least ``keep``) such that the rest
    make a consistent model (:func:`consistent`), after ``settle`` (which takes a jump
    into the model or out again as the references make it evident); the one of least
    :func:`misfit` where several are. A reference left out alone may be taken back
    when others show the same (a tear of the scan: the references on the rows before it
    are each the only one there until a second is scanned). Where no such set is, the
    reference the others contradict most (:meth:`ScanDrift.worst`) goes."""
    if not scan.rows or (not aside and consistent(scan, p)):
        return [], []
    keys = sorted([*scan.rows, *aside], key=str)
    whole = scan.trial()
    for key, (rows, seen) in aside.items():
        whole.restore(key, rows, seen)
    for m in range(0, min(len(aside) + most, len(keys) - keep) + 1):
        best = None
        for out in combinations(keys, m):
            trial = whole.trial()
            for key in out:
                trial.remove(key)
            settle(trial)
            if consistent(trial, p):
                fit = misfit(trial)
                if best is None or fit < best[0]:
                    best = (fit, set(out))
        if best is not None:
            return [k for k in keys if k in best[1] and k in scan.rows], [k for k in keys if k in aside and k not in best[1]]
    return [scan.worst()[0]], []
