"""The step loop compiled by numba gives the numbers of the numpy reference loop (docs/sim.md: 1e-12)."""

from __future__ import annotations

import numpy as np
import pytest

from bac_sim import kernels
from bac_sim.controllers import ControllerII
from bac_sim.driver import DriverModel
from bac_sim.engine import make_model, simulate
from bac_sim.problems import get_problem
from bac_sim.scenarios import get_scenario

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

TOLERANCE = 1e-12  # relative, on every KPI part (documented in docs/sim.md)


def _both(fn):  # type: ignore[no-untyped-def]
    return fn("numpy"), fn("numba")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bump_c1", "road_c1", "road_c2"])
@pytest.mark.parametrize("noisy", [False, True])
def test_compiled_loop_matches_the_numpy_reference(name: str, noisy: bool) -> None:
    p = get_problem(name)
    sc = p.scenario
    rng = np.random.default_rng(5)
    n = 12
    thetas = p.bounds[:, 0] + rng.random((n, p.dim)) * (p.bounds[:, 1] - p.bounds[:, 0])
    thetas[0] = p.bounds[:, 1]  # the firmest corner: bump stops and end-stop protection are reached
    raw = p.raw(thetas)
    start, duration = sc.batch_timing()
    if noisy:  # as Problem.noisy_j draws them: each run its own speed profile, start and window shift
        lead_m = sc.lead_s * sc.speed
        duration = (1.6 * lead_m + sc.window_length_s * sc.speed) / (0.95 * sc.speed) + sc.tail_s
        driver = DriverModel(start_offset_std=0.2 * lead_m)
        drive, _ = driver.draw(sc.speed, start, duration + 0.2, n, np.random.default_rng(1))
        shift = 0.1 * np.random.default_rng(2).standard_normal(n) * (1.0 if sc.mode == "distance" else 0.01)
    else:
        from bac_sim.driver import constant_drive

        drive, shift = constant_drive(sc.speed, start, duration + 0.1), None
    model = make_model(dt=sc.dt)

    def run(kernel: str):  # type: ignore[no-untyped-def]
        from bac_sim.controllers import make_controller

        ctrl = make_controller(p.definition, raw)
        return simulate(model, sc.road, ctrl, drive, duration, sc.window, window_shift=shift, kernel=kernel)

    ref, fast = _both(run)
    for part in ("sum_az2", "sum_q2", "max_travel"):
        a, b = getattr(ref, part), getattr(fast, part)
        np.testing.assert_allclose(b, a, rtol=TOLERANCE, atol=0, err_msg=part)
    np.testing.assert_array_equal(fast.count, ref.count)
    np.testing.assert_array_equal(fast.lift_off, ref.lift_off)
    assert np.all(ref.j > 0)


def test_recorded_runs_match_including_the_commands() -> None:
    sc = get_scenario("bump")
    p = get_problem("road_c2")
    start, duration = sc.batch_timing()
    from bac_sim.driver import constant_drive

    drive = constant_drive(sc.speed, start, duration + 0.1)
    model = make_model(dt=sc.dt)
    raw = np.array([np.full(20, 500.0), np.linspace(0.0, 1000.0, 20)])
    recs = []
    for kernel in ("numpy", "numba"):
        res = simulate(model, sc.road, ControllerII(raw), drive, duration, sc.window, record=True, kernel=kernel)
        assert res.recording is not None
        recs.append(res.recording)
    np.testing.assert_allclose(recs[1].X, recs[0].X, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(recs[1].command, recs[0].command, rtol=1e-9, atol=1e-12)
    assert p.dim == 20


def test_kernel_choice_follows_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BAC_SIM_KERNEL", "numpy")
    assert kernels.kernel_choice() == "numpy"
    monkeypatch.setenv("BAC_SIM_KERNEL", "")
    assert kernels.kernel_choice() == "numba"
    assert kernels.kernel_choice("numpy") == "numpy"
    with pytest.raises(ValueError, match="kernel must be one of"):
        kernels.kernel_choice("fortran")
