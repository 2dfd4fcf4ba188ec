"""Figures of the simulated car: ``python -m bac_sim.plots OUTDIR`` writes PNGs.

* ``j_bump_c1.png``, ``j_road_c1.png``: J of Controller I over the (front, rear) damping grid with
  the true optimum (the paper's fig. 7, as ground truth);
* ``spectra_road.png``: spectra of the seat-rail vertical acceleration and of the pitch rate on the
  test road for minimum, maximum and the optimal constant damping (the paper's fig. 12 trade-off:
  firm wins at the ~1 Hz body resonance, soft above a few Hz);
* ``bump_time.png``: the seat-rail vertical acceleration and pitch rate over the bump window for the
  same three calibrations (the paper's fig. 10).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import welch

from bac_common.console import say
from bac_sim.engine import SEAT_DEFAULT
from bac_sim.problems import get_problem

FloatArray = np.ndarray[Any, Any]


def _signals(problem_name: str, thetas: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Seat-rail a_z and pitch rate (n, B) of nominal runs, their times, and the step."""
    p = get_problem(problem_name)
    res = p.simulate(thetas, record=True)
    rec = res.recording
    assert rec is not None
    from bac_sim.engine import make_model

    m = make_model(dt=p.scenario.dt)
    X = rec.X  # (n, 22, B)
    acc = np.einsum("ij,njb->nib", m.acc_x, X[:, :14]) + np.einsum("ij,njb->nib", m.acc_u, X[:, 14:])
    acc += m.acc_const[None, :, None]
    az = acc[:, 0] - SEAT_DEFAULT[0] * acc[:, 1] + SEAT_DEFAULT[1] * acc[:, 2]
    q = X[:, 8]
    t = rec.t
    w = (t[:, None] >= res.window_start[None, :]) & (t[:, None] < res.window_end[None, :])
    az = np.where(w, az, np.nan)
    q = np.where(w, q, np.nan)
    return t, az, q, p.scenario.dt


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bac_sim.plots", description=__doc__.splitlines()[0])
    ap.add_argument("outdir")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(args.outdir)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("bump_c1", "road_c1"):
        p = get_problem(name)
        axes = np.array(p.truth["grid"]["axes"])
        grid = np.array(p.truth["grid"]["j"])
        fig, ax = plt.subplots(figsize=(5.5, 4.5))
        cs = ax.contourf(axes[1], axes[0], grid, levels=30, cmap="viridis")
        fig.colorbar(cs, ax=ax, label="J = RMS(a_z) + RMS(pitch rate)")
        ax.plot(p.theta_star[1], p.theta_star[0], "r*", ms=14, label=f"optimum J* = {p.j_star:.4f}")
        ax.set_xlabel("damping_rear")
        ax.set_ylabel("damping_front")
        ax.set_title(f"{name}: Controller I on the {p.scenario.name} (ground truth)")
        ax.legend(loc="lower left")
        fig.tight_layout()
        fig.savefig(out / f"j_{name}.png", dpi=120)
        plt.close(fig)
    labels = ("minimum damping", "maximum damping", "optimum")
    for name, fname in (("road_c1", "spectra_road.png"), ("bump_c1", "bump_time.png")):
        p = get_problem(name)
        th = np.array([[0.0, 0.0], [1.0, 1.0], p.theta_star])
        t, az, q, dt = _signals(name, th)
        fig, axs = plt.subplots(2, 1, figsize=(7, 6))
        for b, label in enumerate(labels):
            a_b, q_b = az[:, b], q[:, b]
            keep = ~np.isnan(a_b)
            if name == "road_c1":
                f, pa = welch(a_b[keep], fs=1 / dt, nperseg=4096)
                _, pq = welch(q_b[keep], fs=1 / dt, nperseg=4096)
                axs[0].semilogy(f, pa, label=label)
                axs[1].semilogy(f, pq, label=label)
            else:
                axs[0].plot(t[keep] - t[keep][0], a_b[keep], label=label)
                axs[1].plot(t[keep] - t[keep][0], q_b[keep], label=label)
        if name == "road_c1":
            for ax, what in zip(axs, ("PSD a_z [(m/s^2)^2/Hz]", "PSD pitch rate [(rad/s)^2/Hz]"), strict=True):
                ax.set_xlim(0, 15)
                top = max(line.get_ydata().max() for line in ax.get_lines())
                ax.set_ylim(top * 1e-5, top * 3)
                ax.set_ylabel(what)
            axs[1].set_xlabel("frequency [Hz]")
            axs[0].set_title("test road, Controller I: the soft/firm trade-off")
        else:
            axs[0].set_ylabel("a_z [m/s^2]")
            axs[1].set_ylabel("pitch rate [rad/s]")
            axs[1].set_xlabel("time from the pre-trigger [s]")
            axs[0].set_title("speed bump, Controller I, KPI window")
        axs[0].legend()
        fig.tight_layout()
        fig.savefig(out / fname, dpi=120)
        plt.close(fig)
    say(f"wrote figures to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
