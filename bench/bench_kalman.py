"""Drift filter benchmark: prediction error versus measurement interval, and call costs.

For each measurement interval and noise level it simulates two hours of drift (a steady
0.3 nm/s plus a velocity random walk of 5e-4 nm/s per √s), measures the offset at that
interval and reports, just before each measurement (what the executor relies on to
place a local scan), the RMS error of the filter's predicted offset, of holding the
last measured offset (no filter), the mean ``r_max`` (3 σ), the share of errors inside
``r_max``, and the RMS velocity error after ten minutes. Then the cost of each call.

Run: ``python bench/bench_kalman.py [--seeds N]``.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from nanoasm.drift import (
    DriftFilter,
    DriftFilterParams,
    predict,
    predict_sqrt,
    psd_sqrt,
    smooth,
    update,
    update_sqrt,
)

V0 = np.array([0.3, -0.1])  # nm/s
WALK = 5e-4  # nm/s per √s


def simulate(rng: np.random.Generator, t_end: float, h: float = 0.5):
    """Truth ``(t, offset, velocity)`` on a fine grid (trapezoidal position)."""
    n = round(t_end / h)
    v = np.vstack([V0, V0 + np.cumsum(rng.standard_normal((n, 2)) * WALK * math.sqrt(h), axis=0)])
    x = np.vstack([np.zeros(2), np.cumsum(h * 0.5 * (v[1:] + v[:-1]), axis=0)])
    return np.arange(n + 1) * h, x, v


def track(seed: int, interval: float, sigma: float, t_end: float = 7200.0) -> dict:
    rng = np.random.default_rng(seed)
    _, xg, vg = simulate(rng, t_end)
    f = DriftFilter(DriftFilterParams(q=WALK**2, measurement_std=sigma))
    held = np.zeros(2)
    pred_err, hold_err, rmax, inside, vel_err = [], [], [], [], []
    for t in np.arange(interval, t_end, interval):
        k = round(t / 0.5)
        est = f.offset(t)
        r = f.r_max(t)
        e = np.hypot(*(est.offset - xg[k]))
        pred_err.append(e)
        hold_err.append(np.hypot(*(held - xg[k])))
        rmax.append(r)
        inside.append(e <= r)
        z = xg[k] + rng.normal(0.0, sigma, 2)
        f.measure(t, z)
        held = z
        if t > 600.0:
            vel_err.append(np.hypot(*(f.x[2:] - vg[k])))
    track_ = smooth(f.history)
    idx = [i for i, h in enumerate(f.history) if h.kind == "measure"]
    times = np.array([f.history[i].t for i in idx])
    truth = xg[np.round(times / 0.5).astype(int)]
    filt = np.array([f.history[i].x[:2] for i in idx])
    return {
        "pred": np.array(pred_err), "hold": np.array(hold_err), "rmax": np.array(rmax),
        "inside": np.array(inside), "vel": np.array(vel_err),
        "filt": np.hypot(*(filt - truth).T), "smooth": np.hypot(*(track_.offset[idx] - truth).T),
    }


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(np.concatenate(a)))))


def accuracy(seeds: int) -> None:
    print("interval  sigma | predicted  held  | r_max  inside | vel err | filtered  smoothed")
    print("   s       nm   |  rms nm   rms nm |  nm      %    |  nm/s   |  rms nm    rms nm")
    for interval in (10.0, 30.0, 60.0, 120.0, 300.0):
        for sigma in (1.0, 2.0):
            runs = [track(s, interval, sigma) for s in range(seeds)]
            print(f"{interval:7.0f}  {sigma:5.1f} | {rms([r['pred'] for r in runs]):7.2f} "
                  f"{rms([r['hold'] for r in runs]):7.2f}  | "
                  f"{np.mean(np.concatenate([r['rmax'] for r in runs])):5.1f} "
                  f"{100 * np.mean(np.concatenate([r['inside'] for r in runs])):6.1f} | "
                  f"{rms([r['vel'] for r in runs]):7.4f} | "
                  f"{rms([r['filt'] for r in runs]):7.2f} {rms([r['smooth'] for r in runs]):9.2f}")


def per_call(fn, n: int = 2000) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1e6


def costs() -> None:
    rng = np.random.default_rng(0)
    x, P, R, z = np.zeros(4), np.diag([100.0, 100.0, 0.25, 0.25]), 2.25 * np.eye(2), np.ones(2)
    L = psd_sqrt(P)
    f = DriftFilter()
    state = {"t": 0.0}

    def measure_one():
        state["t"] += 30.0
        f.measure(state["t"], rng.normal(0, 2, 2))

    g = DriftFilter()
    state_g = {"t": 0.0}

    def measure_four():
        state_g["t"] += 30.0
        g.measure_many(state_g["t"], rng.normal(0, 2, (4, 2)))

    rows = [
        ("predict + update (Joseph, covariance)", lambda: update(*predict(x, P, 30.0, 1e-6), z, R)),
        ("predict_sqrt + update_sqrt", lambda: update_sqrt(*predict_sqrt(x, L, 30.0, 1e-6), z, R)),
        ("DriftFilter.measure (1 offset)", measure_one),
        ("DriftFilter.measure_many (4 offsets)", measure_four),
        ("DriftFilter.offset", lambda: f.offset(f.time + 10.0)),
        ("DriftFilter.r_max", lambda: f.r_max(f.time + 10.0)),
    ]
    for name, fn in rows:
        print(f"{name:40s} {per_call(fn):8.1f} µs")
    t0 = time.perf_counter()
    smooth(f.history)
    print(f"{'smooth (' + str(len(f.history)) + ' steps)':40s} {(time.perf_counter() - t0) * 1e3:8.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    accuracy(args.seeds)
    print()
    costs()


if __name__ == "__main__":
    main()
