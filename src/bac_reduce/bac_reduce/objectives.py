"""Batch objectives of the simulation phase: what a campaign's runs are evaluated on.

An objective is a small picklable value (it travels to worker processes and Dask workers):
it knows its calibration definition and evaluates a batch of calibrations at once, each
row with its own run-to-run noise (``evaluate``) or noise-free (``true_j``, for checks and
the validation table; a real car has no such thing).

* :class:`SimulatedCar`: the batch simulator of ``bac_sim`` (``road_c2`` = Controller II on
  the 1.5 km test road), optionally through a reduced definition;
* :class:`SyntheticObjective`: a cheap analytic J whose important parameters and groups are
  known (tests, demos, trying the options in seconds).

An objective may also have ``evaluate_runs(thetas, rng) -> (J, {outcome: (n,)})``: the same runs' J and the
outcomes they report besides it (the simulator's suspension travel; issue 23). The campaigns then record them
and tell them to the engine, and ``result.json`` stores them per run (what a car campaign's outcome limits take
as their prior: ``bac_agent.transfer.load_outcome_sources``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from bac_common.paramspace import CalibrationDefinition, RawParameter

FloatArray = NDArray[np.float64]
Rng = np.random.Generator | Sequence[np.random.Generator]  # one for a batch, or one per row

_CACHE: dict[tuple[str, str], Any] = {}


@runtime_checkable
class BatchObjective(Protocol):
    """What the campaigns need from a problem."""

    @property
    def definition(self) -> CalibrationDefinition: ...

    def evaluate(self, thetas: FloatArray, rng: Rng) -> FloatArray:
        """(n, d) tuned values (the definition's dimensions, in order) -> (n,) noisy J; ``rng`` one generator for
        the batch or one per row (each row's noise from its own generator, whatever else is in the batch)."""
        ...

    def true_j(self, thetas: FloatArray) -> FloatArray:
        """(n, d) -> (n,) noise-free J."""
        ...

    def with_definition(self, definition: CalibrationDefinition) -> BatchObjective:
        """The same problem calibrated through another definition (e.g. the reduced one)."""
        ...

    @property
    def label(self) -> str: ...


def _definition_key(definition: Mapping[str, Any] | None) -> str:
    return "" if definition is None else json.dumps(definition, sort_keys=True)


@dataclass(frozen=True)
class SimulatedCar:
    """A ``bac_sim`` batch problem (default ``road_c2``), optionally re-based on another definition.

    ``definition`` is the definition as a dict (picklable, small); ``None`` = the problem's own.
    The simulator is built once per process and cached.
    """

    problem: str = "road_c2"
    definition_dict: Mapping[str, Any] | None = None
    noisy: bool = True  # evaluate = runs with run-to-run noise (driver, alignment, IMU); False = noise-free runs

    def _problem(self) -> Any:
        key = (self.problem, _definition_key(self.definition_dict))
        if key not in _CACHE:
            from bac_sim.problems import get_problem

            p = get_problem(self.problem)
            if self.definition_dict is not None:
                p = p.with_definition(CalibrationDefinition.from_dict(self.definition_dict))
            _CACHE[key] = p
        return _CACHE[key]

    @property
    def definition(self) -> CalibrationDefinition:
        d: CalibrationDefinition = self._problem().definition
        return d

    @property
    def label(self) -> str:
        return f"{self.problem} ({self.definition.name}, {len(self.definition.dimensions)} tuned)"

    def evaluate(self, thetas: FloatArray, rng: Rng) -> FloatArray:
        if not self.noisy:
            return self.true_j(thetas)
        return np.asarray(self._problem().noisy_j(np.atleast_2d(thetas), rng), dtype=float)

    def evaluate_runs(self, thetas: FloatArray, rng: Rng) -> tuple[FloatArray, dict[str, FloatArray]]:
        """``evaluate`` and the outcomes each run reports (``bac_sim.problems.Problem.noisy_runs``:
        ``max_travel_mm``, ``lift_off_ms``; issue 23). Noise-free (``noisy`` False): J noise-free, no outcomes."""
        if not self.noisy:
            return self.true_j(thetas), {}
        j, outcomes = self._problem().noisy_runs(np.atleast_2d(thetas), rng)
        return np.asarray(j, dtype=float), {k: np.asarray(v, dtype=float) for k, v in outcomes.items()}

    def true_j(self, thetas: FloatArray) -> FloatArray:
        return np.asarray(self._problem().true_j(np.atleast_2d(thetas)), dtype=float)

    def with_definition(self, definition: CalibrationDefinition) -> SimulatedCar:
        return SimulatedCar(self.problem, definition.to_dict(), self.noisy)

    # ground truth of the full problem (None when the simulator has none stored)
    def reference(self) -> tuple[float, float] | None:
        p = self._problem()
        try:
            return float(p.j_star), float(p.j_med)
        except Exception:
            return None


# --- a synthetic problem whose answer is known --------------------------------------------------
@dataclass(frozen=True)
class SyntheticTerm:
    """A parameter's contribution: ``weight · (r - optimum)^2`` in relative units r (0..1)."""

    name: str
    optimum: float
    weight: float


def default_terms() -> tuple[SyntheticTerm, ...]:
    """Eight parameters in [0, 1000]: two groups, a single, two discarded (see :class:`SyntheticObjective`)."""
    return (
        SyntheticTerm("q1", 0.8, 0.30),
        SyntheticTerm("q2", 0.8, 0.25),
        SyntheticTerm("q3", 0.8, 0.20),
        SyntheticTerm("q4", 0.2, 0.40),
        SyntheticTerm("q5", 0.0, 0.20),
        SyntheticTerm("q6", 0.0, 0.15),
        SyntheticTerm("q7", 0.5, 0.02),
        SyntheticTerm("q8", 0.3, 0.01),
    )


@dataclass(frozen=True)
class SyntheticObjective:
    """``J(θ) = j0 + Σ w_i (r_i - o_i)^2 + coupling · (r_1 - o_1)(r_4 - o_4)``, r = θ / 1000.

    With :func:`default_terms`: q1, q2, q3 share an optimum at 0.8 of the range (one
    meta-parameter), q5 and q6 at 0 (another), q4 alone at 0.2; q7 and q8 cost at most 0.5 %
    and 0.5 % of J* (discarded at T = 5 %). J* = j0 = 1. Noise: ``noise_rel`` of J, Gaussian
    (the simulator's run noise is about 0.5 %).
    """

    terms: tuple[SyntheticTerm, ...] = field(default_factory=default_terms)
    j0: float = 1.0
    coupling: float = 0.05
    noise_rel: float = 0.005
    lower: float = 0.0
    upper: float = 1000.0
    tuned: tuple[str, ...] = ()
    meta: tuple[tuple[str, tuple[str, ...]], ...] = ()
    fixed: tuple[tuple[str, float], ...] = ()

    @property
    def definition(self) -> CalibrationDefinition:
        from bac_common.paramspace import MetaParameter

        params = tuple(
            RawParameter(t.name, i, self.lower, self.upper, (self.lower + self.upper) / 2, 0.01)
            for i, t in enumerate(self.terms)
        )
        return CalibrationDefinition(
            name="synthetic",
            parameters=params,
            tuned=self.tuned,
            meta=tuple(MetaParameter(n, m, self.lower, self.upper) for n, m in self.meta),
            fixed=dict(self.fixed),
            description="synthetic quadratic J with known groups (bac_reduce.objectives)",
        )

    @property
    def label(self) -> str:
        return f"synthetic ({len(self.definition.dimensions)} tuned)"

    @property
    def optimum(self) -> FloatArray:
        """The raw optimum (every parameter), own units."""
        return np.array([self.lower + t.optimum * (self.upper - self.lower) for t in self.terms])

    def raw_j(self, raw: FloatArray) -> FloatArray:
        """Noise-free J of raw calibrations (n, P)."""
        r = (np.atleast_2d(np.asarray(raw, dtype=float)) - self.lower) / (self.upper - self.lower)
        o = np.array([t.optimum for t in self.terms])
        w = np.array([t.weight for t in self.terms])
        dev = r - o
        j = self.j0 + (dev**2) @ w
        if len(self.terms) >= 4:
            j = j + self.coupling * dev[:, 0] * dev[:, 3]
        return np.asarray(j, dtype=float)

    def _raw(self, thetas: FloatArray) -> FloatArray:
        d = self.definition
        names = [x.name for x in d.dimensions]
        th = np.atleast_2d(np.asarray(thetas, dtype=float))
        rows = [d.expand(dict(zip(names, row, strict=True))) for row in th]
        return np.array([[cal[p] for p in d.parameter_names] for cal in rows])

    def true_j(self, thetas: FloatArray) -> FloatArray:
        return self.raw_j(self._raw(thetas))

    def evaluate(self, thetas: FloatArray, rng: Rng) -> FloatArray:
        j = self.true_j(thetas)
        if isinstance(rng, np.random.Generator):
            z = rng.standard_normal(j.shape)
        else:
            z = np.array([g.standard_normal() for g in rng])
        return np.asarray(j * (1.0 + self.noise_rel * z), dtype=float)

    def with_definition(self, definition: CalibrationDefinition) -> SyntheticObjective:
        if definition.parameter_names != tuple(t.name for t in self.terms):
            raise ValueError("a synthetic objective can only be re-based on a definition of its own parameters")
        return SyntheticObjective(
            self.terms,
            self.j0,
            self.coupling,
            self.noise_rel,
            self.lower,
            self.upper,
            tuple(definition.tuned),
            tuple((m.name, tuple(m.members)) for m in definition.meta),
            tuple(sorted(definition.fixed.items())),
        )

    def reference(self) -> tuple[float, float] | None:
        """(J*, J_med) of the full problem: J* exact, J_med over 4096 random points (seeded)."""
        rng = np.random.default_rng(12345)
        raw = self.lower + rng.random((4096, len(self.terms))) * (self.upper - self.lower)
        return float(np.min(self.raw_j(self.optimum[None, :]))), float(np.median(self.raw_j(raw)))


def objective_names() -> Sequence[str]:
    from bac_sim.problems import PROBLEM_NAMES

    return (*PROBLEM_NAMES, "synthetic")


def make_objective(name: str) -> SimulatedCar | SyntheticObjective:
    """``road_c2`` (or another bac_sim problem) or ``synthetic``."""
    if name == "synthetic":
        return SyntheticObjective()
    from bac_sim.problems import PROBLEM_NAMES

    if name not in PROBLEM_NAMES:
        from bac_reduce.analysis import ReductionError

        raise ReductionError(f"unknown problem {name!r}; known: {', '.join(objective_names())}")
    return SimulatedCar(name)
