"""The car families of the benchmark: reproducible instances, the drawn spread, J and outcomes of real runs."""

from __future__ import annotations

import numpy as np
import pytest

from bac_sim.errors import SimError
from bac_sim.families import CAR_FAMILIES, draw_vehicle, get_family
from bac_sim.vehicle import VehicleParams


def test_instances_are_reproducible_and_differ() -> None:
    fam = get_family("bump_c1")
    a, b, c = fam.instance(3), fam.instance(3), fam.instance(4)
    assert a.vehicle == b.vehicle and a.describe == b.describe
    assert a.vehicle != c.vehicle
    assert 0.01 <= a.noise_rel <= 0.03


def test_vehicle_spread_stays_in_its_ranges() -> None:
    v0 = VehicleParams()
    rng = np.random.default_rng(0)
    for _ in range(50):
        v = draw_vehicle(rng)
        assert 0.8 <= v.sprung_mass / v0.sprung_mass <= 1.2
        assert 0.8 <= v.unsprung_mass_total / v0.unsprung_mass_total <= 1.2
        assert 0.92 <= v.cg_to_front_axle / v0.cg_to_front_axle <= 1.08
        assert 0.8 <= v.spring_rate / v0.spring_rate <= 1.2
        assert 0.8 <= v.tyre_rate / v0.tyre_rate <= 1.2
        assert 0.7 <= v.dampers.soft.rebound_low / v0.dampers.soft.rebound_low <= 1.3
        assert v.dampers.firm.compression_high > v.dampers.soft.compression_high


@pytest.mark.parametrize("family", CAR_FAMILIES)
def test_tests_are_drawn_in_the_families_ranges(family: str) -> None:
    for i in range(5):
        d = get_family(family).instance(i).describe
        if family.startswith("bump"):
            assert 20.0 <= d["speed_kmh"] <= 40.0 and 50 <= d["bump_height_mm"] <= 100
        else:
            assert 40.0 <= d["speed_kmh"] <= 80.0 and d["iso_class"] in ("A", "B", "C")


def test_j_and_outcomes_of_runs() -> None:
    inst = get_family("bump_c1").instance(0)
    thetas = np.array([[0.0, 0.0], [1.0, 1.0], [0.3, 0.3]])
    out = inst.evaluate(thetas)
    assert out["j"].shape == (3,) and np.all(out["j"] > 0)
    # soft dampers let the suspension travel further over a bump than firm ones
    assert out["max_travel_mm"][0] > out["max_travel_mm"][1] > 0
    # the nominal car on the same test is another car: another J
    nominal = get_family("bump_c1").nominal(inst)
    assert not np.allclose(nominal.true_j(thetas), out["j"])
    noisy = inst.noisy(np.repeat(thetas[2:], 200, axis=0), np.random.default_rng(1))
    rel = np.std(noisy["j"]) / out["j"][2]
    assert 0.5 * inst.noise_rel < rel < 1.5 * inst.noise_rel


def test_controller_ii_family_runs_through_the_meta_parameters() -> None:
    inst = get_family("road_c2").instance(0)
    assert inst.names == ("m1", "m2")  # the families' own 2-meta-parameter file, not the shipped one (3 since 11-24)
    raw = inst.raw(np.array([[0.0, 1000.0]]))
    assert raw.shape == (1, 20)
    with pytest.raises(SimError):
        inst.raw(np.zeros((1, 3)))
