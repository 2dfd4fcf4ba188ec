"""Batch problems for optimizers: J(theta) of the simulated car, noise-free or with run-to-run noise.

::

    from bac_sim.problems import get_problem, PROBLEM_NAMES   # "bump_c1", "road_c1", "road_c2", "road_c2b"
    p = get_problem("road_c1")
    p.names, p.dim, p.bounds          # tuned dimensions, d, (d, 2) [lower, upper]
    p.true_j(thetas)                  # (n, d) -> (n,) noise-free J
    p.noisy_j(thetas, rng)            # (n, d) -> (n,) J of real simulated runs with run-to-run noise
    p.noisy_runs(thetas, rng)         # the same runs' J and their outcomes {"max_travel_mm": (n,), "lift_off_ms": (n,)}
    p.j_star, p.theta_star, p.j_med   # true optimum and median J over random parameters
    p.gap(j)                          # (j - j_star) / (j_med - j_star)

J is the paper's eq. 1, RMS(a_z) + RMS(pitch rate) of the seat-rail signals (vehicle frame, gravity
removed) over the scenario's KPI window. ``thetas`` are in the units of the problem's calibration
definition (Controller I: damping commands in [0, 1]; Controller II: counts in [0, 1000]); a value
outside the bounds raises :class:`bac_common.errors.OutOfBoundsError`. A problem can be re-based on
a reduced definition (meta-parameters, fixed values) with :meth:`Problem.with_definition`.

Noise (``noisy_j``): each run is driven by the :class:`~bac_sim.driver.DriverModel` (road: cruise-control
set-point error 0.3 km/h, slow speed fluctuation 0.15 km/h; bump: speed held by foot, 0.8 and 0.3 km/h;
scattered start), cut with a residual
alignment error (0.2 m on the road, 2 ms at the bump) and measured by an IMU with white noise
(0.02 m/s^2 and 0.002 rad/s per sample at 500 Hz). The resulting J noise is about 0.5-1 % of J; the
figures measured at the optimum are stored in ``data/ground_truth.json`` (``noise_rel``).

Outcomes (``noisy_runs``, issue 23): what each of those runs reports besides J, under the names the car
campaign's limits use (``bac_sim.families.OUTCOMES``): ``max_travel_mm``, the largest suspension travel from
static of any corner during the run, and ``lift_off_ms``, how long a wheel left the road. They are the simulated
run's own values (its driver's speed and start), with no sensor noise added: drawing one would change the
random stream, and so J, of every later run.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from bac_common.paramspace import CalibrationDefinition
from bac_sim.controllers import (
    controller_i_definition,
    controller_ii_definition,
    controller_iib_definition,
    make_controller,
)
from bac_sim.driver import Drive, DriverModel, constant_drive
from bac_sim.engine import BatchResult, make_model, simulate
from bac_sim.errors import SimError
from bac_sim.parallel import run_split, worker_count
from bac_sim.scenarios import Scenario, get_scenario

FloatArray = np.ndarray[Any, Any]

PROBLEM_NAMES = ("bump_c1", "road_c1", "road_c2", "road_c2b")
GROUND_TRUTH_PATH = Path(__file__).resolve().parent / "data" / "ground_truth.json"
_SCENARIO_OF = {"bump_c1": "bump", "road_c1": "road", "road_c2": "road", "road_c2b": "road"}
# batches at least this many run-seconds long are split over the worker processes
PARALLEL_MIN_RUN_SECONDS = 1200.0


@dataclass(frozen=True)
class MeasurementNoise:
    """Run-to-run noise of ``noisy_j`` beyond the driver (see the module doc)."""

    align_m: float = 0.2  # residual alignment error of a road section, m (1 sigma)
    align_s: float = 0.002  # residual alignment error of an event window, s
    accel_noise: float = 0.02  # IMU vertical acceleration noise per sample, m/s^2
    gyro_noise: float = 0.002  # IMU pitch-rate noise per sample, rad/s


def _evaluate(
    scenario_name: str,
    definition_dict: Mapping[str, Any],
    raw: FloatArray,
    drive: Drive,
    duration: float,
    window_shift: FloatArray | None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Worker: simulate a slice of a batch; returns (sum a_z^2, sum q^2, count, max travel m, lift-off steps)."""
    sc = get_scenario(scenario_name)
    definition = CalibrationDefinition.from_dict(definition_dict)
    model = make_model(dt=sc.dt)
    ctrl = make_controller(definition, raw)
    res = simulate(model, sc.road, ctrl, drive, duration, sc.window, window_shift=window_shift)
    return res.sum_az2, res.sum_q2, res.count, res.max_travel, res.lift_off


def _slice_drive(drive: Drive, sl: slice) -> Drive:
    if drive.batch == 1:
        return drive
    return Drive(drive.t, drive.v[:, sl], drive.s[:, sl])


@dataclass(frozen=True)
class Problem:
    """One calibration problem on the simulated car (see the module doc)."""

    name: str
    scenario: Scenario
    definition: CalibrationDefinition
    driver: DriverModel = field(default_factory=DriverModel)
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    truth: Mapping[str, Any] = field(default_factory=dict)

    # --- the search space -----------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.definition.dimensions)

    @property
    def dim(self) -> int:
        return len(self.definition.dimensions)

    @property
    def bounds(self) -> FloatArray:
        return np.array([[d.lower, d.upper] for d in self.definition.dimensions], dtype=float)

    def with_definition(self, definition: CalibrationDefinition) -> Problem:
        """The same car and scenario calibrated through another definition of the same controller
        (e.g. the reduced one of the simulation phase); j_star etc. keep the full problem's values."""
        return replace(self, definition=definition)

    def raw(self, thetas: FloatArray) -> FloatArray:
        """Tuned values (n, d) -> raw calibrations (n, P), checked against every bound."""
        th = np.atleast_2d(np.asarray(thetas, dtype=float))
        if th.ndim != 2 or th.shape[1] != self.dim:
            raise SimError(f"{self.name}: thetas must be an (n, {self.dim}) array, got shape {th.shape}")
        names = self.names
        order = self.definition.parameter_names
        out = np.empty((th.shape[0], len(order)))
        for i, row in enumerate(th):
            cal = self.definition.expand(dict(zip(names, row, strict=True)))
            out[i] = [cal[n] for n in order]
        return out

    # --- evaluations ------------------------------------------------------------------------
    def true_j(self, thetas: FloatArray) -> FloatArray:
        """Noise-free J (n,): nominal speed, exact window, ideal IMU."""
        raw = self.raw(thetas)
        start, duration = self.scenario.batch_timing()
        drive = constant_drive(self.scenario.speed, start, duration + 0.1)
        az2, q2, cnt, _, _ = self._run(raw, drive, duration, None)
        return np.asarray(np.sqrt(az2 / cnt) + np.sqrt(q2 / cnt))

    def noisy_j(self, thetas: FloatArray, rng: np.random.Generator | Sequence[np.random.Generator]) -> FloatArray:
        """J (n,) of simulated runs with run-to-run noise (driver, alignment, IMU); see ``noisy_runs``."""
        return self.noisy_runs(thetas, rng)[0]

    def noisy_runs(
        self, thetas: FloatArray, rng: np.random.Generator | Sequence[np.random.Generator]
    ) -> tuple[FloatArray, dict[str, FloatArray]]:
        """J (n,) of simulated runs with run-to-run noise (driver, alignment, IMU), and the outcomes each run
        reports (``max_travel_mm``, ``lift_off_ms``: the module doc); the same J as ``noisy_j``.

        ``rng``: one generator for the whole batch, or one per run (a sequence of n, the same generator may
        appear several times): then each run's noise comes from its own generator, in the order of the rows,
        so a run's J does not depend on the other runs simulated in the same batch (e.g. campaigns of a
        simulation phase batched together on one core or spread over a cluster).
        """
        raw = self.raw(thetas)
        n = raw.shape[0]
        sc = self.scenario
        start, _ = sc.batch_timing()
        lead_m = sc.lead_s * sc.speed
        driver = replace(self.driver, start_offset_std=min(self.driver.start_offset_std, 0.2 * lead_m))
        slowest = sc.speed * (1 - 4 * driver.speed_error_std / sc.speed - 0.02)
        run_s = (1.6 * lead_m + sc.window_length_s * sc.speed) / slowest + sc.tail_s
        align = self.noise.align_m if sc.mode == "distance" else self.noise.align_s
        if isinstance(rng, np.random.Generator):
            drive, _ = driver.draw(sc.speed, start, run_s + 0.2, n, rng)
            shift = align * rng.standard_normal(n)
        else:
            rngs = list(rng)
            if len(rngs) != n:
                raise SimError(f"{self.name}: {len(rngs)} random generators for {n} runs")
            drives = [driver.draw(sc.speed, start, run_s + 0.2, 1, g)[0] for g in rngs]
            drive = Drive(drives[0].t, np.hstack([d.v for d in drives]), np.hstack([d.s for d in drives]))
            shift = align * np.array([g.standard_normal() for g in rngs])
        az2, q2, cnt, travel, lift = self._run(raw, drive, run_s, shift)
        ms_a = az2 / cnt
        ms_q = q2 / cnt
        # IMU white noise: exact distribution of the measured mean square over cnt samples
        for mean_square, sigma in ((ms_a, self.noise.accel_noise), (ms_q, self.noise.gyro_noise)):
            if isinstance(rng, np.random.Generator):
                z = rng.standard_normal(n)
                chi = rng.chisquare(cnt)
            else:
                z = np.empty(n)
                chi = np.empty(n)
                for i, g in enumerate(rngs):
                    z[i] = g.standard_normal()
                    chi[i] = g.chisquare(cnt[i])
            cross = 2 * sigma * np.sqrt(mean_square / cnt) * z
            power = sigma**2 * chi / cnt
            np.add(mean_square, cross + power, out=mean_square)
        j = np.asarray(np.sqrt(np.maximum(ms_a, 0)) + np.sqrt(np.maximum(ms_q, 0)))
        outcomes = {
            "max_travel_mm": np.asarray(1000.0 * travel, dtype=float),
            "lift_off_ms": np.asarray(1000.0 * sc.dt * lift, dtype=float),
        }
        return j, outcomes

    def _run(
        self, raw: FloatArray, drive: Drive, duration: float, shift: FloatArray | None
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        n = raw.shape[0]
        workers = worker_count()
        parallel = workers > 1 and n * duration >= PARALLEL_MIN_RUN_SECONDS
        parts = workers if parallel else 1
        edges = np.linspace(0, n, parts + 1).round().astype(int)
        jobs = []
        dd = self.definition.to_dict()
        for a, b in itertools.pairwise(edges):
            if b > a:
                sl = slice(int(a), int(b))
                jobs.append(
                    (
                        self.scenario.name,
                        dd,
                        raw[sl],
                        _slice_drive(drive, sl),
                        duration,
                        None if shift is None else shift[sl],
                    )
                )
        results = run_split(_evaluate, jobs, parallel)
        az2 = np.concatenate([r[0] for r in results])
        q2 = np.concatenate([r[1] for r in results])
        cnt = np.concatenate([r[2] for r in results])
        if np.any(cnt <= 0):
            raise SimError(f"{self.name}: a run has no sample in its KPI window")
        travel = np.concatenate([r[3] for r in results])
        lift = np.concatenate([r[4] for r in results])
        return az2, q2, cnt, travel, lift

    def simulate(self, thetas: FloatArray, record: bool = False) -> BatchResult:
        """One nominal batch in this process, with every KPI part (and the recording if asked)."""
        raw = self.raw(thetas)
        start, duration = self.scenario.batch_timing()
        drive = constant_drive(self.scenario.speed, start, duration + 0.1)
        model = make_model(dt=self.scenario.dt)
        return simulate(
            model,
            self.scenario.road,
            make_controller(self.definition, raw),
            drive,
            duration,
            self.scenario.window,
            record=record,
        )

    # --- ground truth -----------------------------------------------------------------------
    def _truth(self, key: str) -> Any:
        if key not in self.truth:
            raise SimError(
                f"{self.name}: no stored ground truth '{key}' in {GROUND_TRUTH_PATH}; "
                "regenerate it with `bac ground-truth`"
            )
        return self.truth[key]

    @property
    def j_star(self) -> float:
        return float(self._truth("j_star"))

    @property
    def theta_star(self) -> FloatArray:
        return np.asarray(self._truth("theta_star"), dtype=float)

    @property
    def j_med(self) -> float:
        return float(self._truth("j_med"))

    @property
    def noise_rel(self) -> float:
        """Relative J noise (std / mean) of noisy_j at theta_star, as stored."""
        return float(self.truth.get("noise_rel", math.nan))

    def gap(self, j: FloatArray | float) -> FloatArray:
        """Normalized optimality gap: 0 at the optimum, 1 at the median of random calibrations."""
        return np.asarray((np.asarray(j, dtype=float) - self.j_star) / (self.j_med - self.j_star))


def load_ground_truth(path: Path = GROUND_TRUTH_PATH) -> dict[str, Any]:
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    return dict(data.get("problems", {}))


@lru_cache(maxsize=8)
def get_problem(name: str) -> Problem:
    """One of :data:`PROBLEM_NAMES`."""
    if name not in PROBLEM_NAMES:
        raise SimError(f"unknown problem {name!r}; known: {', '.join(PROBLEM_NAMES)}")
    definitions = {"c1": controller_i_definition, "c2": controller_ii_definition, "c2b": controller_iib_definition}
    definition = definitions[name.split("_")[1]]()
    truth = load_ground_truth().get(name, {})
    scenario = get_scenario(_SCENARIO_OF[name])
    # at 30 km/h most cruise controls are off: the driver holds the speed by foot
    driver = (
        DriverModel(speed_error_std=0.8 / 3.6, speed_fluctuation_std=0.3 / 3.6)
        if scenario.name == "bump"
        else DriverModel()
    )
    return Problem(name, scenario, definition, driver=driver, truth=truth)
