"""Scenarios: a road, the speed it is driven at and the part of a run that is scored.

* ``bump``: the speed bump at 30 km/h; KPI window 2.5 s from a 0.3 s pre-trigger before the front
  wheels reach the bump (paper sec. IV-D: "the same 2.5 s time window").
* ``road``: the 1.5 km test road at 60 km/h; KPI window the whole section (paper sec. IV-E).
* a path to a road file (``.csv`` / ``.npz``, see :mod:`bac_sim.roads`): its metadata says what is
  scored (``kpi_start_m``/``kpi_end_m``, or ``event_m``) and may give ``speed_kmh``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from bac_sim.engine import KpiWindow
from bac_sim.errors import ScenarioError
from bac_sim.roads import Road, build_test_road, load_road, speed_bump_road

BUMP_SPEED_KMH = 30.0
ROAD_SPEED_KMH = 60.0
BUMP_PRE_TRIGGER_S = 0.3
BUMP_WINDOW_S = 2.5
SCENARIO_NAMES = ("bump", "road")


@dataclass(frozen=True)
class Scenario:
    """A road, its target speed (m/s), the KPI window and the simulation step used for it."""

    name: str
    road: Road
    speed: float
    window: KpiWindow
    dt: float  # simulation step of batch evaluations (s)
    lead_s: float  # batch runs start this long before the window (transients die out)
    tail_s: float  # and end this long after it

    @property
    def mode(self) -> str:
        return self.window.mode

    @property
    def window_start_m(self) -> float:
        """Front-axle position where the scored window starts (nominal run)."""
        if self.window.mode == "distance":
            return self.window.start_m
        return self.window.event_m - self.window.pre_s * self.speed

    @property
    def window_length_s(self) -> float:
        """Duration of the scored window of a nominal run (s)."""
        if self.window.mode == "distance":
            return (self.window.end_m - self.window.start_m) / self.speed
        return self.window.length_s

    def batch_timing(self) -> tuple[float, float]:
        """Start position (front axle, m) and duration (s) of a batch run at the nominal speed."""
        start = self.window_start_m - self.lead_s * self.speed
        return start, self.lead_s + self.window_length_s + self.tail_s


@lru_cache(maxsize=8)
def get_scenario(name: str, speed_kmh: float | None = None) -> Scenario:
    """``bump``, ``road`` or a road file; ``speed_kmh`` overrides the scenario's target speed."""
    if name == "bump":
        speed = (speed_kmh or BUMP_SPEED_KMH) / 3.6
        window = KpiWindow("event", event_m=0.0, pre_s=BUMP_PRE_TRIGGER_S, length_s=BUMP_WINDOW_S)
        return Scenario("bump", speed_bump_road(), speed, window, dt=0.001, lead_s=0.7, tail_s=0.05)
    if name == "road":
        road = build_test_road()
        speed = (speed_kmh or ROAD_SPEED_KMH) / 3.6
        window = KpiWindow("distance", start_m=float(road.meta["kpi_start_m"]), end_m=float(road.meta["kpi_end_m"]))
        return Scenario("road", road, speed, window, dt=0.0025, lead_s=2.0, tail_s=0.5)
    path = Path(name)
    if not path.suffix:
        raise ScenarioError(f"unknown scenario {name!r}: use one of {SCENARIO_NAMES} or a road file (.csv, .npz)")
    road = load_road(path)
    meta = road.meta
    kmh = speed_kmh or float(meta.get("speed_kmh", ROAD_SPEED_KMH))
    if "event_m" in meta:
        window = KpiWindow(
            "event",
            event_m=float(meta["event_m"]),
            pre_s=float(meta.get("pre_trigger_s", BUMP_PRE_TRIGGER_S)),
            length_s=float(meta.get("window_s", BUMP_WINDOW_S)),
        )
        dt = 0.001
    elif "kpi_start_m" in meta and "kpi_end_m" in meta:
        window = KpiWindow("distance", start_m=float(meta["kpi_start_m"]), end_m=float(meta["kpi_end_m"]))
        dt = 0.0025
    else:
        raise ScenarioError(
            f"road file {path} says nothing about what to score: add '# kpi_start_m: ...' and '# kpi_end_m: ...' "
            "(a road section) or '# event_m: ...' (a single event) header lines"
        )
    return Scenario(path.stem, road, kmh / 3.6, window, dt=dt, lead_s=1.0, tail_s=0.5)
