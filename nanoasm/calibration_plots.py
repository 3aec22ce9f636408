"""A plot per step of ``nanoasm calibrate`` (the seed's Fig. 3.9, 3.11, 3.12, 3.14, 3.19 in kind).

:func:`plot_steps` writes ``force_curve.png``, ``baselines.png``, ``substrate_loop.png``,
``slope_loops.png`` (with the two curves of eq. 3.26-3.27 crossing at the solution) and
``edge.png`` into a folder, each atomically. matplotlib is imported here only.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from nanoasm.executor.calibration import Calibration

NAMES = ("force_curve", "baselines", "substrate_loop", "slope_loops", "edge")


def _force_curve(fig, cal: Calibration) -> None:
    st = cal.steps["force_curve"]
    f = st["fit"]
    ax1, ax2 = fig.subplots(1, 2)
    ax1.plot(st["z"], st["s_n"], ".", ms=2, label="S_n")
    ax1.plot(st["z"], st["s_l"], ".", ms=2, label="S_l")
    ax1.axvline(f.contact_z, color="0.6", lw=0.8)
    ax1.set(xlabel="piezo z (nm)", ylabel="signal (V)", title=f"force curve: K_n = {f.normal_gain.value:.2f} "
            f"± {f.normal_gain.sigma:.2f} nm/V (eq. 3.13)")
    ax1.invert_xaxis()
    ax1.legend()
    c = st["z"] < f.contact_z - 10.0
    ax2.plot(st["s_n"][c], st["s_l"][c], ".", ms=2)
    ax2.set(xlabel="S_n (V)", ylabel="S_l (V)", title=f"pressing: alpha = {f.crosstalk.value:.4f} "
            f"± {f.crosstalk.sigma:.4f} (seed 3.5)")


def _baselines(fig, cal: Calibration) -> None:
    m = cal.baselines
    x0, y0 = m.origin
    extent = (x0 / 1000, (x0 + m.side) / 1000, y0 / 1000, (y0 + m.side) / 1000)
    for ax, arr, name in zip(fig.subplots(1, 2), (m.a, m.b), ("A(i, j), S_n", "B(i, j), S_l")):
        im = ax.imshow(arr, extent=extent, origin="upper", cmap="viridis")
        fig.colorbar(im, ax=ax, label="V")
        ax.set(xlabel="scanner x (µm)", ylabel="scanner y (µm)", title=f"free-air baseline {name} at contact")


def _substrate(fig, cal: Calibration) -> None:
    st = cal.steps["substrate_loop"]
    rows, dw = st["rows"], st["fit"]
    ax1, ax2 = fig.subplots(1, 2)
    ax1.plot(rows[:, 0], rows[:, 1], "o-", label="trace")
    ax1.plot(rows[:, 0], rows[:, 2], "s-", label="retrace")
    ax1.set(xlabel="S_n (V)", ylabel="mean S_l (V)", title="friction loop on the substrate")
    ax1.legend()
    ax2.plot(rows[:, 0], st["half"], "o")
    ax2.plot(rows[:, 0], np.polyval(np.polyfit(rows[:, 0], st["half"], 1), rows[:, 0]), "-")
    ax2.set(xlabel="S_n (V)", ylabel="half-width W (V)", title=f"dW/dS_n = {dw.value:.4f} ± {dw.sigma:.4f}; "
            f"mu_ts = {cal.values['mu_ts'].value:.4f}")


def _slope(fig, cal: Calibration) -> None:
    st = cal.steps["slope_loops"]
    sf = st["fit"]
    ax1, ax2, ax3 = fig.subplots(1, 3)
    ax1.plot(st["s"], st["heights"], ".", ms=3)
    ax1.set(xlabel="along the line (nm)", ylabel="height (nm)", title=f"slope: {sf.tilt.value:.2f} deg")
    rows = st["rows"]
    ax2.plot(rows[:, 0], -rows[:, 1] / st["g_v"], "o-", label="trace")
    ax2.plot(rows[:, 0], -rows[:, 2] / st["g_v"], "s-", label="retrace")
    ax2.set(xlabel="S_n (V)", ylabel="lateral signal against the slope (V)",
            title=f"dS_l/dS_n: {sf.slopes[0].value:.4f} down, {sf.slopes[1].value:.4f} up (Fig. 3.11)")
    ax2.legend()
    # eq. 3.26 and 3.27 as (k_l K_l / h) against mu: the crossing is the solution (Fig. 3.12)
    th, k, k_n = math.radians(sf.tilt.value), cal.values["k"].value, cal.values["K_n"].value
    mu = np.linspace(0.0, 0.9 * min(math.tan(th), 1.0 / math.tan(th)), 200)
    for slope, sign, name in ((sf.slopes[0].value, -1, "eq. 3.26 (down)"), (sf.slopes[1].value, 1, "eq. 3.27 (up)")):
        lam = np.arctan(mu)
        ax3.plot(mu, np.tan(th + sign * lam) / slope * k * k_n, label=name)
    ax3.plot([sf.mu.value], [sf.lateral_gain.value], "ko")
    ax3.set(xlabel="mu", ylabel="k_l K_l / h (nN/V)", title=f"{sf.lateral_gain.value:.2f} nN/V, mu = "
            f"{sf.mu.value:.4f}", ylim=(0, 3 * sf.lateral_gain.value))
    ax3.legend()


def _edge(fig, cal: Calibration) -> None:
    rows, c2 = cal.steps["edge"]["rows"], cal.steps["edge"]["fit"]
    ax = fig.subplots()
    # the steady drift of the step taken out, as the fit does
    design = np.column_stack([np.ones(len(rows)), rows[:, 2] - rows[:, 2].mean(), rows[:, 0]])
    coef = np.linalg.lstsq(design, rows[:, 1], rcond=None)[0]
    still = rows[:, 1] - coef[1] * (rows[:, 2] - rows[:, 2].mean())
    ax.plot(rows[:, 0], still, "o")
    ax.plot(rows[:, 0], coef[0] + coef[2] * rows[:, 0], "-")
    ax.set(xlabel="S_n before the step (V)", ylabel="piezo along the lever axis at the climb, drift removed (nm)",
           title=f"C2 = {c2.value:.2f} ± {c2.sigma:.2f} nm/V (eq. 3.30-3.34)")


def plot_steps(cal: Calibration, folder: Path) -> list[Path]:
    """One PNG per step in ``folder``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    from nanoasm.fileio import write_atomic

    out = []
    for name, draw, size in zip(NAMES, (_force_curve, _baselines, _substrate, _slope, _edge),
                                ((12, 4.5), (12, 4.5), (12, 4.5), (17, 4.5), (6, 4.5))):
        fig = plt.figure(figsize=size, layout="constrained")
        try:
            draw(fig, cal)
            buf = io.BytesIO()
            fig.savefig(buf, format="png", dpi=90)
        finally:
            plt.close(fig)
        path = Path(folder) / f"{name}.png"
        write_atomic(path, buf.getvalue())
        out.append(path)
    return out


__all__ = ["NAMES", "plot_steps"]
