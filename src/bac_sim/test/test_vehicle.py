"""The full-car model: statics, modes, frequency response (issue 3, must show)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bac_sim.controllers import ControllerI
from bac_sim.driver import constant_drive
from bac_sim.engine import make_model, simulate
from bac_sim.errors import ModelError
from bac_sim.roads import Road
from bac_sim.vehicle import G, VehicleParams, build_linear_model


@pytest.fixture
def flat_road() -> Road:
    """A perfectly flat road from -100 m to 2000 m."""
    n = 21001
    return Road("flat", -100.0, 0.1, np.zeros(n), np.zeros(n), {"kpi_start_m": 0.0, "kpi_end_m": 100.0})


def test_static_deflection_under_gravity_is_mg_over_k() -> None:
    """Let the car drop from its unloaded geometry (springs and tyres at free length) and settle."""
    p = VehicleParams()
    lin = build_linear_model(p)
    # linear viscous dampers so that the drop settles; gravity is the model's own input
    c = 3000.0
    C = np.zeros((14, 14))
    C[7:, 7:] = -np.linalg.inv(lin.M) @ (lin.D.T @ (c * np.eye(4)) @ lin.D)
    A = lin.A + C
    sol = solve_ivp(lambda t, x: A @ x + lin.bg, (0.0, 20.0), np.zeros(14), rtol=1e-9, atol=1e-12)
    q = sol.y[:7, -1]
    spring = -(lin.D @ q)  # compression of each suspension
    tyre = -q[3:]  # compression of each tyre
    loads = p.corner_sprung_loads  # m_s g b / 2L front, m_s g a / 2L rear
    np.testing.assert_allclose(spring, loads / p.wheel_rates, rtol=1e-6)
    np.testing.assert_allclose(tyre, (loads + p.unsprung_mass * G) / p.tyre_rate, rtol=1e-6)
    # the whole car: m g = k_eq * deflection, corner by corner
    front_total = spring[0] + tyre[0]
    k_eq = 1 / (1 / p.wheel_rates[0] + 1 / p.tyre_rate)
    assert front_total == pytest.approx((loads[0] + p.unsprung_mass * G * k_eq / p.tyre_rate) / k_eq, rel=1e-6)
    # and the analytic static equilibrium the simulator starts from is that state
    np.testing.assert_allclose(lin.static_deflection, -loads / p.wheel_rates, rtol=1e-9)


def test_simulator_holds_the_static_equilibrium_on_a_flat_road(flat_road: Road) -> None:
    m = make_model()
    res = simulate(m, flat_road, ControllerI(np.array([[0.5, 0.5]])), constant_drive(10.0, 0.0, 6.0), 5.0, record=True)
    assert res.recording is not None
    x = res.recording.X[:, :14, 0]
    np.testing.assert_allclose(x, np.repeat(m.linear.x_static[None], x.shape[0], axis=0), atol=1e-9)
    assert res.j[0] < 1e-6


def test_modes_heave_near_1_to_1_5_hz_and_wheel_hop_10_to_15_hz() -> None:
    lin = build_linear_model(VehicleParams())
    freqs, shapes = lin.modes()
    body = freqs[:3]
    wheel = freqs[3:]
    heave = body[np.argmax(np.abs(shapes[0, :3]))]
    assert 1.0 <= heave <= 1.5
    assert np.all((wheel >= 10.0) & (wheel <= 15.0))


def test_passive_frequency_response_peaks() -> None:
    lin = build_linear_model(VehicleParams())
    f = np.linspace(0.3, 25.0, 2000)
    soft = lin.passive_frequency_response(f, 800.0)
    firm = lin.passive_frequency_response(f, 4000.0)
    low = f < 4
    heave_peak = f[low][np.argmax(soft["accel_z"][low] / (2 * np.pi * f[low]) ** 2)]
    assert 1.0 <= heave_peak <= 1.5
    wheel_peak = f[~low][np.argmax(soft["wheel_fl"][~low])]
    assert 10.0 <= wheel_peak <= 15.0

    # the trade-off of the paper: firm damping wins at the body resonance, soft damping above it
    def at(hz: float) -> int:
        return int(np.argmin(np.abs(f - hz)))

    assert firm["accel_z"][at(heave_peak)] < 0.6 * soft["accel_z"][at(heave_peak)]
    assert soft["accel_z"][at(5.0)] < 0.8 * firm["accel_z"][at(5.0)]


def test_simulated_free_heave_oscillation_frequency(flat_road: Road) -> None:
    """Lift the body 2 cm and let go on soft dampers: the heave mode, measured in the time domain."""
    m = make_model()
    offset = np.zeros(14)
    offset[0] = 0.02
    ctrl = ControllerI(np.array([[0.0, 0.0]]))
    res = simulate(m, flat_road, ctrl, constant_drive(0.01, 0.0, 8.0), 8.0, record=True, initial_offset=offset)
    assert res.recording is not None
    z = res.recording.X[:, 0, 0] - m.linear.x_static[0]
    t = res.recording.t
    assert z[0] == pytest.approx(0.02)
    up = t[1:][(z[1:] > 0) & (z[:-1] <= 0)]  # upward zero crossings, one per period
    assert len(up) >= 3
    freq = 1 / np.mean(np.diff(up[:3]))
    assert 1.0 <= freq <= 1.5
    # lightly damped: the second swing still has a good part of the first one's amplitude
    assert 0.2 * 0.02 < z[t > up[0]].max() < 0.02


def test_bad_vehicle_parameters_are_refused() -> None:
    with pytest.raises(ModelError, match="sprung_mass"):
        VehicleParams(sprung_mass=-1.0)
    with pytest.raises(ModelError, match="between the axles"):
        VehicleParams(cg_to_front_axle=3.5)
