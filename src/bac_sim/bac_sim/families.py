"""Families of simulated cars: the same calibration task on cars that differ as real cars do.

A **family** is a calibration task (a controller and a kind of test); an **instance** is one car of
it, drawn from the family's spread around the nominal vehicle of :class:`~bac_sim.vehicle.VehicleParams`,
with its own test conditions. Optimizers are measured over instances they were never tuned on
(``bench/bo_efficiency.py``; docs/agent.md, "Problem families"), and the nominal vehicle on the same test
stands in for the *simulator* of a car (the simulation phase knows the test but not the exact car).

Families (:data:`CAR_FAMILIES`):

* ``bump_c1`` / ``bump_c2``: a round-top bump of random size (50-100 mm high, 0.6-3.7 m long), crossed at
  20-40 km/h; the KPI window is the paper's 2.5 s from 0.3 s before the front wheels reach it;
* ``road_c1`` / ``road_c2``: a 250 m section of random road (ISO 8608 class A, B or C, its own seed) at
  40-80 km/h;
* ``*_c1``: Controller I (constant damping front and rear, 2 parameters in [0, 1]);
  ``*_c2``: Controller II through its meta-parameter file (``data/family_controller_ii_2meta.yaml``: the
  shipped ``controller_ii_reduced`` of 2026-11-23, 2 meta-parameters in [0, 1000], the other parameters fixed
  as the simulation phase left them; kept fixed, apart from the file ``bac reduce`` ships).

Each instance draws (uniformly, seeded by family and index) sprung and unsprung mass (±20 %), the centre of
gravity (±8 % of the front-axle distance), pitch and roll inertia (±20 %), spring and tyre rates (±20 %), and
the dampers: the range between Φ_min and Φ_max (the soft curve ×0.7-1.3, the firm one ×0.8-1.2) and their shape
(knee velocities ×0.7-1.4, high-speed slopes ×0.8-1.25, independently in rebound and compression). Index 0 of a
family's *nominal* instance is the paper's car (:meth:`CarFamily.nominal`).

Every evaluation is a batch of :func:`bac_sim.engine.simulate` runs at the nominal speed and exact window
(the noise-free J), through the public simulator API only. Besides J an instance reports **outcomes** of each
run, the quantities a calibration engineer sets limits on: ``max_travel_mm``, the largest suspension travel
from static of any corner (the bump stops sit at 75 mm in compression, 85 mm in rebound), and
``lift_off_ms``, how long a wheel left the road. ``noisy`` adds run-to-run noise: J times (1 + σ ε) with σ
drawn per instance in [1 %, 3 %], the travel with 1.5 mm + 2 % of its value (a travel sensor and the driver).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from bac_common.paramspace import CalibrationDefinition
from bac_sim.controllers import controller_i_definition, make_controller
from bac_sim.driver import constant_drive
from bac_sim.engine import KpiWindow, make_model, simulate
from bac_sim.errors import SimError
from bac_sim.roads import ISO8608_CLASSES, Road, envelope_tyre, iso8608_tracks, speed_bump_road
from bac_sim.scenarios import BUMP_PRE_TRIGGER_S, BUMP_WINDOW_S, Scenario
from bac_sim.vehicle import DamperCurve, DamperMap, VehicleParams

FloatArray = np.ndarray[Any, Any]

CAR_FAMILIES = ("bump_c1", "road_c1", "bump_c2", "road_c2")
OUTCOMES = ("max_travel_mm", "lift_off_ms")
BATCH = 441  # runs per simulate() call (large batches are slower per run: cache)
ROAD_SECTION_M = 250.0
ROAD_RUN_IN_M = 60.0
ROAD_RUN_OUT_M = 40.0
NOISE_RANGE = (0.01, 0.03)  # run-to-run J noise, relative, drawn per instance
TRAVEL_NOISE_MM = 1.5
TRAVEL_NOISE_REL = 0.02


def with_run_noise(out: dict[str, FloatArray], noise_rel: float, rng: np.random.Generator) -> dict[str, FloatArray]:
    """Noise-free J and outcomes -> a run's: J relative noise ``noise_rel``, travel TRAVEL_NOISE_MM +
    TRAVEL_NOISE_REL of it (std); ``out`` is changed and returned."""
    n = out["j"].shape[0]
    out["j"] = out["j"] * (1.0 + noise_rel * rng.standard_normal(n))
    t = out["max_travel_mm"]
    out["max_travel_mm"] = t + (TRAVEL_NOISE_MM + TRAVEL_NOISE_REL * t) * rng.standard_normal(n)
    return out


def _seed(*parts: object) -> int:
    """A stable 64-bit seed from names and numbers (Python's hash() is salted per process)."""
    h = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(h[:8], "little")


FAMILY_C2_DEFINITION = Path(__file__).resolve().parent / "data" / "family_controller_ii_2meta.yaml"


def controller_ii_reduced_definition() -> CalibrationDefinition:
    """The *_c2 families' Controller II meta-parameter file: ``bac reduce``'s output for the test road as it was
    when the families' truths were computed (2 meta-parameters), kept apart from the shipped
    ``controller_ii_reduced`` (3 since 2026-11-24) so that a benchmark's problems do not move with it."""
    if not FAMILY_C2_DEFINITION.exists():
        raise SimError(f"the families' definition {FAMILY_C2_DEFINITION} is missing (reinstall bac_sim)")
    return CalibrationDefinition.load(FAMILY_C2_DEFINITION)


def draw_vehicle(rng: np.random.Generator, base: VehicleParams | None = None) -> VehicleParams:
    """A car of the family's spread around ``base`` (the nominal sedan): see the module doc."""
    b = base or VehicleParams()

    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    mass = u(0.8, 1.2)
    dm = b.dampers
    soft_k, firm_k = u(0.7, 1.3), u(0.8, 1.2)
    hi_r, hi_c = u(0.8, 1.25), u(0.8, 1.25)

    def scaled(c: DamperCurve, k: float) -> DamperCurve:
        return DamperCurve(
            k * c.rebound_low, k * hi_r * c.rebound_high, k * c.compression_low, k * hi_c * c.compression_high
        )

    soft = scaled(dm.soft, soft_k)
    firm = scaled(dm.firm, firm_k)
    # the firm curve stays above the soft one everywhere (DamperMap checks it): keep a 20 % margin
    firm = DamperCurve(
        max(firm.rebound_low, 1.2 * soft.rebound_low),
        max(firm.rebound_high, 1.2 * soft.rebound_high),
        max(firm.compression_low, 1.2 * soft.compression_low),
        max(firm.compression_high, 1.2 * soft.compression_high),
    )
    dampers = DamperMap(soft, firm, dm.knee_rebound * u(0.7, 1.4), dm.knee_compression * u(0.7, 1.4))
    return replace(
        b,
        sprung_mass=b.sprung_mass * mass,
        unsprung_mass_total=b.unsprung_mass_total * u(0.8, 1.2),
        cg_to_front_axle=b.cg_to_front_axle * u(0.92, 1.08),
        pitch_inertia=b.pitch_inertia * mass * u(0.8, 1.2) / math.sqrt(mass),
        roll_inertia=b.roll_inertia * mass * u(0.8, 1.2) / math.sqrt(mass),
        spring_rate=b.spring_rate * u(0.8, 1.2),
        tyre_rate=b.tyre_rate * u(0.8, 1.2),
        dampers=dampers,
    )


@lru_cache(maxsize=64)
def bump_scenario(height_m: float, length_m: float, speed_kmh: float) -> Scenario:
    """A round-top bump of this size crossed at this speed (the paper's KPI window)."""
    road = speed_bump_road(height=height_m, length=length_m)
    window = KpiWindow("event", event_m=0.0, pre_s=BUMP_PRE_TRIGGER_S, length_s=BUMP_WINDOW_S)
    return Scenario(
        f"bump_{1000 * height_m:.0f}mm_{length_m:.1f}m",
        road,
        speed_kmh / 3.6,
        window,
        dt=0.001,
        lead_s=0.7,
        tail_s=0.05,
    )


@lru_cache(maxsize=64)
def road_scenario(iso_class: str, seed: int, speed_kmh: float) -> Scenario:
    """A ``ROAD_SECTION_M`` section of ISO 8608 road of this class and seed, driven at this speed."""
    if iso_class not in ISO8608_CLASSES:
        raise SimError(f"unknown ISO 8608 class {iso_class!r}; known: {', '.join(ISO8608_CLASSES)}")
    ds = 0.05
    length = ROAD_RUN_IN_M + ROAD_SECTION_M + ROAD_RUN_OUT_M
    left, right = iso8608_tracks(length, ds, ISO8608_CLASSES[iso_class], np.random.default_rng(seed))
    s0 = -ROAD_RUN_IN_M
    road = Road(
        f"iso_{iso_class}_{seed}",
        s0,
        ds,
        envelope_tyre(left, ds),
        envelope_tyre(right, ds),
        {"kpi_start_m": 0.0, "kpi_end_m": ROAD_SECTION_M, "seed": seed, "iso_class": iso_class},
    )
    window = KpiWindow("distance", start_m=0.0, end_m=ROAD_SECTION_M)
    return Scenario(road.name, road, speed_kmh / 3.6, window, dt=0.0025, lead_s=2.0, tail_s=0.3)


@dataclass(frozen=True)
class CarInstance:
    """One car of a family on its test: J and the outcomes of calibrations (see the module doc)."""

    family: str
    index: int
    vehicle: VehicleParams
    scenario: Scenario
    definition: CalibrationDefinition
    noise_rel: float  # run-to-run J noise (std / J)
    describe: Mapping[str, Any] = field(default_factory=dict)  # what was drawn, for reports

    @property
    def name(self) -> str:
        return f"{self.family}#{self.index}"

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.definition.dimensions)

    @property
    def dim(self) -> int:
        return len(self.definition.dimensions)

    @property
    def bounds(self) -> FloatArray:
        return np.array([[d.lower, d.upper] for d in self.definition.dimensions], dtype=float)

    def raw(self, thetas: FloatArray) -> FloatArray:
        """Tuned values (n, d) -> raw calibrations (n, P), checked against every bound."""
        th = np.atleast_2d(np.asarray(thetas, dtype=float))
        if th.ndim != 2 or th.shape[1] != self.dim:
            raise SimError(f"{self.name}: thetas must be an (n, {self.dim}) array, got shape {th.shape}")
        order = self.definition.parameter_names
        out = np.empty((th.shape[0], len(order)))
        for i, row in enumerate(th):  # expansion through the meta-parameters: a few µs per calibration
            cal = self.definition.expand(dict(zip(self.names, row, strict=True)))
            out[i] = [cal[n] for n in order]
        return out

    def evaluate(self, thetas: FloatArray) -> dict[str, FloatArray]:
        """Noise-free J and outcomes (each (n,)) of calibrations ``thetas`` (n, d)."""
        raw = self.raw(thetas)
        sc = self.scenario
        start, duration = sc.batch_timing()
        model = make_model(self.vehicle, dt=sc.dt)
        j, travel, lift = [], [], []
        for a in range(0, raw.shape[0], BATCH):
            part = raw[a : a + BATCH]
            drive = constant_drive(sc.speed, start, duration + 0.1)
            res = simulate(
                model, sc.road, make_controller(self.definition, part, self.vehicle), drive, duration, sc.window
            )
            if np.any(res.count <= 0):
                raise SimError(f"{self.name}: a run has no sample in its KPI window")
            j.append(res.j)
            travel.append(res.max_travel)
            lift.append(res.lift_off)
        return {
            "j": np.concatenate(j),
            "max_travel_mm": 1000.0 * np.concatenate(travel),
            "lift_off_ms": 1000.0 * sc.dt * np.concatenate(lift),
        }

    def true_j(self, thetas: FloatArray) -> FloatArray:
        return self.evaluate(thetas)["j"]

    def noisy(self, thetas: FloatArray, rng: np.random.Generator) -> dict[str, FloatArray]:
        """J and outcomes of runs with run-to-run noise (see the module doc)."""
        return with_run_noise(self.evaluate(thetas), self.noise_rel, rng)

    def noisy_j(self, thetas: FloatArray, rng: np.random.Generator) -> FloatArray:
        return self.noisy(thetas, rng)["j"]

    def with_vehicle(self, vehicle: VehicleParams, label: str = "nominal") -> CarInstance:
        """The same test and controller on another car (e.g. the nominal one: the simulator of this car)."""
        return replace(self, vehicle=vehicle, describe={**dict(self.describe), "vehicle": label})


@dataclass(frozen=True)
class CarFamily:
    """Draws the instances of one of :data:`CAR_FAMILIES`."""

    name: str

    def __post_init__(self) -> None:
        if self.name not in CAR_FAMILIES:
            raise SimError(f"unknown car family {self.name!r}; known: {', '.join(CAR_FAMILIES)}")

    @property
    def definition(self) -> CalibrationDefinition:
        return controller_i_definition() if self.name.endswith("c1") else controller_ii_reduced_definition()

    def _test(self, rng: np.random.Generator) -> tuple[Scenario, dict[str, Any]]:
        if self.name.startswith("bump"):
            h = float(rng.uniform(0.05, 0.10))
            length = float(rng.uniform(0.6, 3.7))
            kmh = float(rng.uniform(20.0, 40.0))
            return bump_scenario(round(h, 3), round(length, 2), round(kmh, 1)), {
                "bump_height_mm": round(1000 * h),
                "bump_length_m": round(length, 2),
                "speed_kmh": round(kmh, 1),
            }
        iso = str(rng.choice(["A", "B", "C"]))
        seed = int(rng.integers(0, 10_000))
        kmh = float(rng.uniform(40.0, 80.0))
        return road_scenario(iso, seed, round(kmh, 1)), {
            "iso_class": iso,
            "road_seed": seed,
            "speed_kmh": round(kmh, 1),
        }

    def instance(self, index: int) -> CarInstance:
        """Instance ``index`` (>= 0): a car and a test, the same on every machine."""
        if index < 0:
            raise SimError(f"instance index must be >= 0, got {index}")
        rng = np.random.default_rng(_seed("bac_sim.families", self.name, index))
        scenario, test = self._test(rng)
        vehicle = draw_vehicle(rng)
        noise = float(rng.uniform(*NOISE_RANGE))
        v0 = VehicleParams()
        describe = {
            **test,
            "sprung_mass_kg": round(vehicle.sprung_mass),
            "unsprung_mass_kg": round(vehicle.unsprung_mass_total),
            "cg_to_front_axle_m": round(vehicle.cg_to_front_axle, 3),
            "pitch_inertia_kgm2": round(vehicle.pitch_inertia),
            "spring_rate_rel": round(vehicle.spring_rate / v0.spring_rate, 3),
            "tyre_rate_rel": round(vehicle.tyre_rate / v0.tyre_rate, 3),
            "soft_rel": round(vehicle.dampers.soft.rebound_low / v0.dampers.soft.rebound_low, 3),
            "firm_rel": round(vehicle.dampers.firm.rebound_low / v0.dampers.firm.rebound_low, 3),
            "noise_pct": round(100 * noise, 2),
        }
        return CarInstance(self.name, index, vehicle, scenario, self.definition, noise, describe)

    def nominal(self, instance: CarInstance) -> CarInstance:
        """The simulator of ``instance``: the nominal vehicle on the same test."""
        return instance.with_vehicle(VehicleParams(), "nominal")


def get_family(name: str) -> CarFamily:
    return CarFamily(name)


__all__ = [
    "CAR_FAMILIES",
    "OUTCOMES",
    "CarFamily",
    "CarInstance",
    "bump_scenario",
    "controller_ii_reduced_definition",
    "draw_vehicle",
    "get_family",
    "road_scenario",
]
