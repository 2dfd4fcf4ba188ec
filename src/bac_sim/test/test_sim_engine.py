"""The batch integrator against an independent adaptive reference, and its convergence."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bac_sim.controllers import ControllerI
from bac_sim.driver import constant_drive
from bac_sim.engine import SEAT_DEFAULT, KpiWindow, make_model, road_under_wheels, simulate
from bac_sim.scenarios import get_scenario
from bac_sim.vehicle import VehicleParams, build_linear_model

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


def reference_bump_j(c_front: float, c_rear: float) -> float:
    """J of the bump run by scipy's adaptive RK45 on the continuous nonlinear model (the oracle)."""
    sc = get_scenario("bump")
    p = VehicleParams()
    lin = build_linear_model(p)
    m = make_model(dt=sc.dt)
    start, duration = sc.batch_timing()
    v = sc.speed
    cmd = np.array([c_front, c_front, c_rear, c_rear])
    dm = p.dampers
    Minv_rows = lin.A[7:10], lin.Bf[7:10], lin.bg[7:10]

    kr, kc = dm.knee_rebound, dm.knee_compression
    lo, hi = dm.basis_coefficients(dm.soft), dm.basis_coefficients(dm.firm)
    coef = lo[:, None] + (hi - lo)[:, None] * cmd[None, :]  # (4 basis, 4 corners)
    dist = sc.road.distance
    offsets = np.array([0.0, 0.0, p.wheelbase, p.wheelbase])
    tracks = (sc.road.left, sc.road.right, sc.road.left, sc.road.right)

    def forces(t: float, x: np.ndarray) -> np.ndarray:
        s = start + v * t - offsets
        r = np.array([np.interp(s[i], dist, tracks[i]) for i in range(4)])
        vel = lin.D @ x[7:]
        phi = (
            coef[0] * vel
            + coef[1] * np.abs(vel)
            + coef[2] * np.maximum(vel - kr, 0)
            + coef[3] * np.minimum(vel + kc, 0)
        )
        travel = lin.D @ x[:7] - m.static_travel
        stop = -p.bump_stop_rate * (
            np.maximum(travel - p.travel_rebound, 0) + np.minimum(travel + p.travel_compression, 0)
        )
        f = np.empty(12)
        f[:4] = -phi + stop
        f[4:8] = p.tyre_rate * np.maximum(x[3:7] - r, 0.0)
        f[8:] = r
        return f

    def rhs(t: float, x: np.ndarray) -> np.ndarray:
        fr = forces(t, x)
        return lin.A @ x + lin.Bf @ fr[:8] + lin.Br @ fr[8:] + lin.bg

    r0 = road_under_wheels(sc.road, np.array([[start]]), p.wheelbase)[0]
    x0 = m.initial_state(r0)[:, 0]
    t_eval = np.arange(0.0, duration, sc.dt)
    sol = solve_ivp(rhs, (0.0, duration), x0, t_eval=t_eval, rtol=1e-7, atol=1e-9, max_step=0.004)
    assert sol.success
    seat = np.array([1.0, -SEAT_DEFAULT[0], SEAT_DEFAULT[1]])
    az = np.empty(t_eval.size)
    for k, t in enumerate(t_eval):
        f = forces(t, sol.y[:, k])[:8]
        acc = Minv_rows[0] @ sol.y[:, k] + Minv_rows[1] @ f + Minv_rows[2]
        az[k] = seat @ acc
    t_event = (sc.window.event_m - start) / v
    w = (t_eval >= t_event - sc.window.pre_s) & (t_eval < t_event - sc.window.pre_s + sc.window.length_s)
    return float(np.sqrt(np.mean(az[w] ** 2)) + np.sqrt(np.mean(sol.y[8, w] ** 2)))


def engine_j(scenario: str, thetas: np.ndarray, dt: float) -> np.ndarray:
    sc = get_scenario(scenario)
    start, duration = sc.batch_timing()
    res = simulate(
        make_model(dt=dt),
        sc.road,
        ControllerI(thetas),
        constant_drive(sc.speed, start, duration + 0.1),
        duration,
        sc.window,
    )
    return res.j


@pytest.mark.slow
def test_bump_j_matches_an_adaptive_reference() -> None:
    ref = reference_bump_j(0.1, 0.6)
    got = engine_j("bump", np.array([[0.1, 0.6]]), get_scenario("bump").dt)[0]
    assert got == pytest.approx(ref, rel=2e-3)


def test_second_order_convergence_on_the_bump() -> None:
    th = np.array([[0.0, 0.0], [1.0, 1.0], [0.5, 0.3]])
    ref = engine_j("bump", th, 0.00025)
    err = [np.max(np.abs(engine_j("bump", th, dt) / ref - 1)) for dt in (0.002, 0.001)]
    assert err[1] < 1e-3  # the step the bump problem uses
    assert err[0] < 5e-3
    assert err[1] < err[0] / 2.5  # better than first order


def test_road_step_is_accurate_on_a_road_section() -> None:
    """The 2.5 ms step of the road problems against 0.5 ms, on 200 m of the test road."""
    sc = get_scenario("road")
    window = KpiWindow("distance", start_m=900.0, end_m=1100.0)  # symmetric waves: heave, pitch, wheel hop
    th = np.array([[0.0, 0.0], [1.0, 1.0], [0.8, 0.5]])
    js = []
    for dt in (0.0025, 0.0005):
        start = 900.0 - 1.0 * sc.speed
        dur = 1.0 + 200.0 / sc.speed + 0.1
        res = simulate(
            make_model(dt=dt), sc.road, ControllerI(th), constant_drive(sc.speed, start, dur + 0.1), dur, window
        )
        js.append(res.j)
    np.testing.assert_allclose(js[0], js[1], rtol=3e-3)


def test_batch_results_do_not_depend_on_the_batch_they_are_in() -> None:
    th = np.random.default_rng(3).random((7, 2))
    alone = np.array([engine_j("bump", th[i : i + 1], 0.001)[0] for i in (0, 6)])
    together = engine_j("bump", th, 0.001)[[0, 6]]
    np.testing.assert_allclose(together, alone, rtol=1e-9)
