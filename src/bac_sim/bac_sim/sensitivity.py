"""One-at-a-time sensitivity of a problem's J from a good point (paper sec. III-D, eq. 4).

``python -m bac_sim.sensitivity`` sweeps each parameter of Controller II over its range, the others
held at the stored best-known calibration of ``road_c2``, with the noise-free simulator, and prints
the worst-case relative loss ``(max_i s_i - J(theta_bar)) / J(theta_bar)`` of each parameter, its
best value and whether it passes the significance threshold T (5 %). This is the truth the
simulation phase (``bac reduce``), which only sees noisy runs through Gaussian processes, should
approach. ``--reveal`` adds what each parameter means inside the simulated controller.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from bac_common.console import say
from bac_sim.controllers import CONTROLLER_II_PARAMETERS
from bac_sim.problems import PROBLEM_NAMES, Problem, get_problem

FloatArray = np.ndarray[Any, Any]
THRESHOLD = 0.05


@dataclass(frozen=True)
class Sensitivity:
    """Result of a one-at-a-time sweep."""

    names: tuple[str, ...]
    theta: FloatArray  # (d,) the point swept from
    j0: float  # J at theta
    values: FloatArray  # (d, m) swept values of each parameter
    j: FloatArray  # (d, m) J along each sweep

    @property
    def loss(self) -> FloatArray:
        """Worst-case relative loss of each parameter (paper eq. 4)."""
        return np.asarray((self.j.max(axis=1) - self.j0) / self.j0)

    @property
    def best_value(self) -> FloatArray:
        return np.asarray(self.values[np.arange(len(self.names)), np.argmin(self.j, axis=1)])

    def significant(self, threshold: float = THRESHOLD) -> tuple[str, ...]:
        return tuple(n for n, s in zip(self.names, self.loss, strict=True) if s > threshold)


def one_at_a_time(problem: Problem, theta: FloatArray | None = None, points: int = 11) -> Sensitivity:
    """Sweep every dimension of ``problem`` over ``points`` values, the others at ``theta``."""
    th = problem.theta_star if theta is None else np.asarray(theta, dtype=float)
    d = problem.dim
    values = np.linspace(problem.bounds[:, 0], problem.bounds[:, 1], points).T  # (d, m)
    rows = [th]
    for i in range(d):
        for v in values[i]:
            r = th.copy()
            r[i] = v
            rows.append(r)
    j = problem.true_j(np.array(rows))
    return Sensitivity(problem.names, th, float(j[0]), values, j[1:].reshape(d, points))


def format_table(s: Sensitivity, threshold: float = THRESHOLD, reveal: bool = False) -> str:
    meaning = {p.name: f"{p.meaning} [{p.unit}]" for p in CONTROLLER_II_PARAMETERS}
    lines = [f"J at the point swept from: {s.j0:.5f}   significance threshold T = {100 * threshold:.0f} %"]
    header = f"{'param':<14}{'at':>9}{'best':>9}{'J best':>9}{'J worst':>9}{'loss %':>9}  significant"
    if reveal:
        header += "  meaning"
    lines.append(header)
    order = np.argsort(-s.loss)
    for i in order:
        row = (
            f"{s.names[i]:<14}{s.theta[i]:>9.1f}{s.best_value[i]:>9.1f}{s.j[i].min():>9.4f}{s.j[i].max():>9.4f}"
            f"{100 * s.loss[i]:>9.2f}  {'yes' if s.loss[i] > threshold else 'no'}"
        )
        if reveal:
            row += f"          {meaning.get(s.names[i], '')}"
        lines.append(row)
    sig = s.significant(threshold)
    lines.append(f"significant ({len(sig)}/{len(s.names)}): {', '.join(sig)}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bac_sim.sensitivity", description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default="road_c2", choices=PROBLEM_NAMES)
    ap.add_argument("--points", type=int, default=11, help="values per parameter sweep")
    ap.add_argument("--threshold", type=float, default=THRESHOLD, help="significance threshold T")
    ap.add_argument("--theta", type=float, nargs="*", help="point to sweep from (default: the stored best)")
    ap.add_argument("--reveal", action="store_true", help="show what each parameter means in the simulator")
    ap.add_argument("--json", help="also write the sweeps to this JSON file")
    args = ap.parse_args(argv)
    p = get_problem(args.problem)
    s = one_at_a_time(p, np.asarray(args.theta) if args.theta else None, args.points)
    say(format_table(s, args.threshold, args.reveal))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(
                {
                    "problem": p.name,
                    "names": list(s.names),
                    "theta": s.theta.tolist(),
                    "j0": s.j0,
                    "values": s.values.tolist(),
                    "j": s.j.tolist(),
                    "loss": s.loss.tolist(),
                },
                fh,
                indent=1,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
