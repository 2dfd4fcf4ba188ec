"""The true optimum of a calibration definition on the simulated car (for judging the experimental phase).

The simulator stores the ground truth of its full problems (``bac ground-truth``). A definition
written by ``bac reduce`` tunes meta-parameters with the other parameters fixed: its optimum J*
and its median J over random calibrations J_med are those of *that* space. They come from the
``result.json`` of the reduction when it is at hand (its validation measured them), else they are
measured here on the noise-free simulator: J_med over random calibrations, J* by a batched
coordinate search from the best of them and from the reduction's optimum.

The object has what ``bac report`` and the demo need of a truth: ``names``, ``true_j``,
``theta_star``, ``j_star``, ``j_med`` and ``gap``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_reduce.objectives import SimulatedCar

FloatArray = NDArray[np.float64]


class TruthError(BacError):
    """The true optimum of a definition cannot be established."""


@dataclass
class DefinitionTruth:
    """True, noise-free J of a definition's tuned space on a simulated problem, with its optimum."""

    car: SimulatedCar
    theta_star: FloatArray
    j_star: float
    j_med: float
    source: str

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.car.definition.dimensions)

    def true_j(self, thetas: FloatArray) -> FloatArray:
        return self.car.true_j(np.atleast_2d(np.asarray(thetas, dtype=float)))

    def gap(self, j: FloatArray | float) -> FloatArray:
        return np.asarray((np.asarray(j, dtype=float) - self.j_star) / (self.j_med - self.j_star))


def definition_truth(
    definition: CalibrationDefinition,
    problem: str = "road_c2",
    result_json: Path | None = None,
    n_random: int = 256,
    polish_iterations: int = 10,
    seed: int = 0,
) -> DefinitionTruth:
    """J*, θ* and J_med of ``definition``'s tuned space on the simulated ``problem``.

    With ``result_json`` (a ``bac reduce`` result whose reduced definition has the same tuned
    dimensions) the validation's figures are taken; otherwise they are measured (about
    ``n_random`` + 40·d noise-free runs, a few seconds on the batch simulator).
    """
    from bac_reduce.pipeline import polish  # the pipeline imports this module's neighbours

    car = SimulatedCar(problem, definition.to_dict(), noisy=False)
    names = [d.name for d in definition.dimensions]
    bounds = np.array([[d.lower, d.upper] for d in definition.dimensions], dtype=float)
    if result_json is not None and result_json.is_file():
        data = json.loads(result_json.read_text())
        v = data.get("validation") or {}
        opt = v.get("reduced_optimum") or {}
        if set(opt) == set(names) and "j_star_reduced" in v and "j_med_reduced" in v:
            theta = np.array([float(opt[n]) for n in names])
            return DefinitionTruth(car, theta, float(v["j_star_reduced"]), float(v["j_med_reduced"]), str(result_json))
    if not names:
        raise TruthError(f"definition {definition.name!r} tunes nothing")
    rng = np.random.default_rng(seed)
    pts = bounds[:, 0] + rng.random((n_random, bounds.shape[0])) * (bounds[:, 1] - bounds[:, 0])
    j = car.true_j(pts)
    if not np.all(np.isfinite(j)):
        raise TruthError(f"the simulator returned non-finite J for {definition.name!r}")
    x, jx, _ = polish(car.true_j, pts[int(np.argmin(j))], bounds, polish_iterations)
    return DefinitionTruth(
        car,
        np.asarray(x, dtype=float),
        float(jx),
        float(np.median(j)),
        f"measured: median of {n_random} random calibrations, best of them polished on the noise-free simulator",
    )
