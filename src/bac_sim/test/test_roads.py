"""Roads: ISO 8608 roughness level, the test road's sections, files in and out, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.signal import welch

from bac_sim.errors import RoadError, ScenarioError
from bac_sim.roads import ISO8608_N0, build_test_road, iso8608_tracks, load_road, speed_bump_road
from bac_sim.scenarios import get_scenario


def test_iso8608_synthesis_has_the_requested_psd_and_coherence() -> None:
    gd = 64e-6  # class B geometric mean
    ds = 0.05
    left, right = iso8608_tracks(4000.0, ds, gd, np.random.default_rng(1))
    n, p = welch(left, fs=1 / ds, nperseg=8192)
    band = (n > 0.05) & (n < 2.0)
    # Gd(n) (n / n0)^2 is flat at gd for waviness 2
    level = np.median(p[band] * (n[band] / ISO8608_N0) ** 2)  # Welch and ISO 8608 are both one-sided
    assert level == pytest.approx(gd, rel=0.25)
    # long waves common to both tracks, short ones not
    _, pc = welch(left - right, fs=1 / ds, nperseg=8192)
    low = (n > 0.02) & (n < 0.05)
    high = (n > 1.0) & (n < 2.0)
    assert np.median(pc[low] / p[low]) < 0.2
    assert np.median(pc[high] / p[high]) > 1.5


def test_test_road_sections_excite_what_they_should() -> None:
    road = build_test_road()
    s = road.distance
    rough = (s > 50) & (s < 500)
    asym = (s > 600) & (s < 850)
    sym = (s > 950) & (s < 1250)
    run_in = s < -50
    assert np.std(road.left[rough]) > 3 * np.std(road.left[run_in])
    assert np.std(road.left[asym] - road.right[asym]) > 0.01  # left != right: roll
    assert np.std(road.left[sym] - road.right[sym]) < 0.3 * np.std(road.left[sym])  # symmetric waves
    assert np.std(road.left[sym]) > 0.009
    assert road.meta["kpi_end_m"] - road.meta["kpi_start_m"] == 1500.0
    bump = speed_bump_road()
    assert bump.heights(np.array([1.0]))[0][0] == pytest.approx(0.07, abs=0.005)


def test_road_files_round_trip_and_drive_as_scenarios(tmp_path: Path) -> None:
    road = speed_bump_road()
    for suffix in (".csv", ".npz"):
        path = tmp_path / f"bump{suffix}"
        road.save(path)
        back = load_road(path, envelope=False)
        np.testing.assert_allclose(back.left, road.left, atol=2e-6)
        assert back.meta["event_m"] == 0.0
    sc = get_scenario(str(tmp_path / "bump.csv"), 30.0)
    assert sc.mode == "event" and sc.speed == pytest.approx(30 / 3.6)


def test_bad_road_files_say_what_is_wrong(tmp_path: Path) -> None:
    with pytest.raises(RoadError, match="not found"):
        load_road(tmp_path / "missing.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("distance_m,left_m,right_m\n" + "\n".join(f"{i},0.0,nan" for i in range(20)))
    with pytest.raises(RoadError, match="NaN"):
        load_road(bad)
    back = tmp_path / "backwards.csv"
    back.write_text("\n".join(f"{20 - i},0.0,0.0" for i in range(20)))
    with pytest.raises(RoadError, match="increasing"):
        load_road(back)
    plain = tmp_path / "plain.csv"
    plain.write_text("\n".join(f"{i},0.0,0.0" for i in range(20)))
    with pytest.raises(ScenarioError, match="kpi_start_m"):
        get_scenario(str(plain))
    with pytest.raises(ScenarioError, match="unknown scenario"):
        get_scenario("moon")
